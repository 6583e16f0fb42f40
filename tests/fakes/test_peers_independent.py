"""The fake peers speak their protocols from the descriptions (docs/*_protocol.md, the
vendors' documents), never from the drivers they test: a protocol mistake in a driver must not
be mirrored in its peer. No module of fakes/ imports anything of drivers/."""

from __future__ import annotations

import ast
from pathlib import Path

FAKES = Path(__file__).resolve().parents[2] / "fakes"


def _imported(path: Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(("." * node.level) + node.module)
    return out


def test_fakes_import_nothing_of_drivers() -> None:
    modules = sorted(FAKES.glob("*.py"))
    assert len(modules) > 5  # the walk sees the peers
    offenders = {p.name: sorted(m for m in _imported(p) if m.startswith((
        "robid_link.drivers", "drivers", "..drivers"))) for p in modules}
    assert {k: v for k, v in offenders.items() if v} == {}
