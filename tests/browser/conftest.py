"""Headless Chromium from Debian's package, driven by Playwright (never its own browser
download): one browser per test module, a fresh page (and profile) per test, every console
message, page error and request recorded. The modules mark themselves ``browser``."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

CHROMIUM = os.environ.get("ROBID_CHROMIUM", "/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} not found (make system-deps installs Debian's chromium)")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as pw:
        # launch() gives the browser a fresh temporary profile (user-data-dir) of its own
        b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            yield b
        finally:
            b.close()


@dataclass
class Page:
    """A page with what it said and asked for."""

    page: Any
    console: list[tuple[str, str]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)

    def problems(self) -> list[str]:
        """Page errors, console errors and warnings (but the one the tests' own canvas reads
        cause: 'Multiple readback operations using getImageData')."""
        return self.errors + [f"{kind}: {text}" for kind, text in self.console
                              if kind in ("error", "warning") and "getImageData" not in text]


@pytest.fixture
def page(browser: Any) -> Iterator[Page]:
    ctx = browser.new_context(viewport={"width": 1400, "height": 1000})
    pg = Page(ctx.new_page())
    pg.page.on("console", lambda m: pg.console.append((m.type, m.text)))
    pg.page.on("pageerror", lambda e: pg.errors.append(str(e)))
    pg.page.on("request", lambda r: pg.requests.append(r.url))
    try:
        yield pg
    finally:
        ctx.close()
