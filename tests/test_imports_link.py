"""The package's import graph, read from the source (ast, every import incl. those inside
functions and under TYPE_CHECKING): no circle anywhere, the product never imports the fakes,
and no private name is imported across modules of the link side."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: package name → source folder (drivers/ and fakes/ install as robid_link.drivers/.fakes)
PACKAGES = {"robid_link": ROOT / "robid_link", "robid_link.drivers": ROOT / "drivers",
            "robid_link.fakes": ROOT / "fakes"}
#: where a ``from m import _private`` across modules is refused
NO_PRIVATE = ("robid_link.link", "robid_link.drivers", "robid_link.fakes", "robid_link.config",
              "robid_link.cli", "robid_link.yamlio")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg, folder in PACKAGES.items():
        for f in sorted(folder.rglob("*.py")):
            parts = [p for p in f.relative_to(folder).with_suffix("").parts if p != "__init__"]
            out[".".join([pkg, *parts])] = f
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> Iterator[tuple[str, list[str], int]]:
    """``(imported module, names imported from it, line)`` of every absolute or relative
    import in a module, resolved to modules of the package where possible."""
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, [], node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")[: len(name.split(".")) - node.level + is_pkg]
                base = ".".join([*anchor, base] if base else anchor)
            names = [a.name for a in node.names]
            subs = [n for n in names if f"{base}.{n}" in MODULES]
            for n in subs:
                yield f"{base}.{n}", [], node.lineno
            yield base, [n for n in names if n not in subs], node.lineno


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for name, path in MODULES.items():
        for target, _, _ in _imports(name, path):
            if target in MODULES and target != name:
                graph[name].add(target)
    return graph




#: the one circle left, inside the worker's numerical core (identify's load-friction
#: pre-fit borrows diagnose.attach_predictions); the ident/runner.py refactor removes it
def test_config_and_neutral_modules_import_no_wing_back() -> None:
    """config imports no wing, only neutral modules and the door (``jobs``: the file-name rule
    of experiment ids; ``kinds``: the experiment kinds' options); the door imports only
    neutral modules; yamlio, safeyaml, safeopen, atomic and exceptions import nothing of the
    package but each other. (Import circles: ``test_architecture.py``.)"""
    graph = _graph()
    neutral = {"robid_link.yamlio", "robid_link.safeyaml", "robid_link.atomic",
               "robid_link.exceptions", "robid_link.safeopen"}
    door = {"robid_link.jobs", "robid_link.kinds"}
    assert graph["robid_link.config"] <= neutral | door
    for module in door:
        assert graph[module] <= neutral, module
    for module in neutral:
        assert graph[module] <= neutral - {module}, module


def test_the_product_never_imports_the_fakes() -> None:
    bad = [f"{MODULES[name].relative_to(ROOT)}:{line} imports {target}"
           for name in MODULES if not name.startswith("robid_link.fakes")
           for target, _, line in _imports(name, MODULES[name])
           if target == "robid_link.fakes" or target.startswith("robid_link.fakes.")]
    assert not bad, bad


@pytest.mark.parametrize("name", [m for m in MODULES if m.startswith(NO_PRIVATE)])
def test_no_private_name_imported_across_modules(name: str) -> None:
    bad = [f"{MODULES[name].relative_to(ROOT)}:{line}: from {target} import {n}"
           for target, names, line in _imports(name, MODULES[name])
           for n in names if n.startswith("_") and not n.startswith("__") and target != name]
    assert not bad, bad
