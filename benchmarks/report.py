"""`make bench --only report`: the demo's report.html against its budgets — size ≤ 3 MB and
first render ≤ 2 s in headless Chromium (Debian's, driven by Playwright; median of 3 fresh
pages, from navigation start to the page's last figure drawn)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["bench_report", "first_render_ms", "report"]

CHROMIUM = os.environ.get("ROBID_CHROMIUM", "/usr/bin/chromium")
SIZE_BUDGET_MB = 3.0
RENDER_BUDGET_MS = 2000.0


def first_render_ms(url: str, runs: int = 3) -> list[float]:
    """Milliseconds from navigation start until the page's figures are all drawn."""
    from playwright.sync_api import sync_playwright

    out = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run"])
        try:
            for _ in range(runs):
                ctx = browser.new_context(viewport={"width": 1400, "height": 1000})
                page = ctx.new_page()
                page.goto(url)
                page.wait_for_selector("body[data-rendered]", timeout=60_000)
                out.append(float(page.evaluate("window.robidReport.readyMs")))
                ctx.close()
        finally:
            browser.close()
    return out


def bench_report() -> dict[str, float] | None:
    if not os.access(CHROMIUM, os.X_OK):
        return None
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "robid_link.cli", "demo", "--out", "out"],
                       cwd=tmp, check=True, capture_output=True)
        page = Path(tmp) / "out" / "report.html"
        times = sorted(first_render_ms(page.as_uri()))
        return {"size_mb": page.stat().st_size / 1e6, "render_ms": times[len(times) // 2],
                "render_max_ms": times[-1]}


def report(r: dict[str, float] | None) -> None:
    if r is None:
        print(f"report.html: {CHROMIUM} not found (make system-deps), not measured")
        return
    print(f"report.html of the demo: {r['size_mb']:.2f} MB (budget {SIZE_BUDGET_MB:g} MB, "
          f"{r['size_mb'] / SIZE_BUDGET_MB:.2f}× of it); first render in headless Chromium "
          f"{r['render_ms']:.0f} ms median of 3, worst {r['render_max_ms']:.0f} ms (budget "
          f"{RENDER_BUDGET_MS:.0f} ms, {r['render_ms'] / RENDER_BUDGET_MS:.2f}× of it)")
