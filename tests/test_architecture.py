"""The package's import graph, read from the source with ``ast``: no import circle, nothing in
the core imports the fakes, no private name used across modules.

Modules are named as installed: ``drivers/x.py`` is ``robid_link.drivers.x`` and ``fakes/x.py``
is ``robid_link.fakes.x`` (package-dir mapping in pyproject.toml). Imports inside functions
count (a lazy import is still a dependency); imports under ``if TYPE_CHECKING:`` do not.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_DIRS = {"robid_link": ROOT / "robid_link", "robid_link.drivers": ROOT / "drivers",
                "robid_link.fakes": ROOT / "fakes"}

#: private names still used across modules outside robid_link.ident (owned by other branches)


def _private(name: str) -> bool:
    """``_x`` is private; ``__version__`` and other dunders are public by convention."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for pkg, folder in PACKAGE_DIRS.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join([pkg, *parts])] = path
    return out


MODULES = _modules()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _walk_runtime(tree: ast.AST) -> Iterator[ast.AST]:
    """Every node except what sits under ``if TYPE_CHECKING:``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                stack.extend(child.orelse)
                continue
            stack.append(child)


def _resolve(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if _is_package(module) else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def _imports(module: str) -> tuple[set[str], set[tuple[str, str]]]:
    """(modules of the package this one imports, (importer, 'module.private') uses)."""
    tree = ast.parse(MODULES[module].read_text(), str(MODULES[module]))
    deps: set[str] = set()
    private: set[tuple[str, str]] = set()
    aliases: dict[str, str] = {}  # local name → package module it is bound to
    for node in _walk_runtime(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name in MODULES:
                    deps.add(a.name)
                    if a.asname:
                        aliases[a.asname] = a.name
        elif isinstance(node, ast.ImportFrom):
            src = _resolve(module, node)
            for a in node.names:
                sub = f"{src}.{a.name}"
                if sub in MODULES:  # a module (robid_link.ident may be a namespace package)
                    deps.add(sub)
                    aliases[a.asname or a.name] = sub
                    continue
                if src not in MODULES:
                    continue
                deps.add(src)
                if _private(a.name) and src != module:
                    private.add((module, sub))
    for node in _walk_runtime(tree):  # ex._helper(...) on an imported module
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in aliases and _private(node.attr)
                and not node.attr.startswith("__")):
            private.add((module, f"{aliases[node.value.id]}.{node.attr}"))
    deps.discard(module)
    return deps, private


GRAPH: dict[str, set[str]] = {}
PRIVATE: set[tuple[str, str]] = set()
for _name in MODULES:
    GRAPH[_name], _priv = _imports(_name)
    PRIVATE |= _priv


def _cycles(nodes: set[str]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), as sorted lists."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in GRAPH[v] & nodes:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return out


def test_the_walk_sees_the_package() -> None:
    """The checks below mean something only if the walk finds the modules and their edges."""
    assert {"robid_link.ident.fit.identify", "robid_link.ident.fit.design",
            "robid_link.drivers.file_share", "robid_link.fakes.plant",
            "robid_link.link.worker"} <= set(MODULES)
    assert "robid_link.ident.fit.design" in GRAPH["robid_link.ident.fit.identify"]
    assert "robid_link.fakes.plant" in GRAPH["robid_link.fakes.controller"]
    # `from pkg import module`
    assert "robid_link.ident.excite.excitation" in GRAPH["robid_link.cli.robot"]


def test_the_cycle_finder_finds_a_cycle(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(GRAPH, "robid_link.ident.model.robot",
                        GRAPH["robid_link.ident.model.robot"] | {"robid_link.ident.fit.identify"})
    ident = {m for m in MODULES if m.startswith("robid_link.ident.")}
    assert any("robid_link.ident.model.robot" in c for c in _cycles(ident))


def test_no_import_cycle_in_the_worker() -> None:
    assert _cycles({m for m in MODULES if m.startswith("robid_link.ident")}) == []


def test_no_import_cycle_in_the_package() -> None:
    assert _cycles(set(MODULES)) == []


def test_the_core_does_not_import_fakes_or_drivers() -> None:
    offenders = sorted((m, d) for m, deps in GRAPH.items() if not m.startswith(
        ("robid_link.fakes", "robid_link.drivers")) for d in deps
        if d.startswith(("robid_link.fakes", "robid_link.drivers")))
    assert offenders == []


def test_the_link_and_the_worker_meet_only_at_the_door() -> None:
    """link/, drivers/, config and the door import nothing of the worker (``robid_link.ident``:
    its entry point is named in jobs.py and imported by name in the worker process); the
    worker imports nothing of the link."""
    near = ("robid_link.link", "robid_link.drivers", "robid_link.config", "robid_link.jobs",
            "robid_link.kinds")
    offenders = sorted((m, d) for m, deps in GRAPH.items()
                       if m.startswith(near)
                       for d in deps if d.startswith("robid_link.ident"))
    offenders += sorted((m, d) for m, deps in GRAPH.items() if m.startswith("robid_link.ident")
                        for d in deps if d.startswith("robid_link.link"))
    assert offenders == []


def test_no_private_name_across_modules_in_the_worker() -> None:
    assert sorted(p for p in PRIVATE if p[0].startswith("robid_link.ident.")) == []


def test_no_private_name_across_modules() -> None:
    assert sorted(PRIVATE) == []
