"""The import graph against the design document (``docs/design.md``): its rooms table says which
modules make each room, its edges table which rooms may import which. Read from the source with
``ast``: every import counts — at the top, inside functions, under ``TYPE_CHECKING`` — except that
import circles are looked for among runtime imports only. Also: no private name imported across
modules, and at most 12 modules in any package folder.

Modules are named as installed: ``drivers/x.py`` is ``robid_link.drivers.x`` and ``fakes/x.py``
is ``robid_link.fakes.x`` (package-dir mapping in pyproject.toml).
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DESIGN = ROOT / "docs" / "design.md"
PACKAGE_DIRS = {"robid_link": ROOT / "robid_link", "robid_link.drivers": ROOT / "drivers",
                "robid_link.fakes": ROOT / "fakes", "robid_link.examples": ROOT / "examples"}
MAX_MODULES = 12


def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for pkg, folder in PACKAGE_DIRS.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join([pkg, *parts])
            if name not in out or path.name == "__init__.py":  # robid_link.drivers is a folder
                out[name] = path
    return out


MODULES = _modules()


# ----------------------------------------------------------------------------- the document


def _table(marker: str) -> list[tuple[str, str]]:
    """The two-column table between ``<!-- marker:begin -->`` and ``<!-- marker:end -->``."""
    text = DESIGN.read_text()
    m = re.search(rf"<!-- {marker}:begin -->(.*?)<!-- {marker}:end -->", text, re.S)
    assert m, f"{DESIGN}: no {marker} table"
    rows = []
    for line in m.group(1).strip().splitlines()[2:]:  # header and rule
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        assert len(cells) == 2, f"{DESIGN}: {marker} row {line!r}"
        rows.append((cells[0], cells[1]))
    return rows


ROOMS: dict[str, list[str]] = {
    room: re.findall(r"robid_link[\w.]*", cell) for room, cell in _table("rooms")}
EDGES: dict[str, set[str]] = {
    room: {e.strip() for e in cell.split(",") if e.strip()} for room, cell in _table("edges")}


def _matches(module: str, prefix: str) -> bool:
    if prefix.endswith(".__init__"):  # the package itself, not what is under it
        return module == prefix.removesuffix(".__init__")
    return module == prefix or module.startswith(prefix + ".")


def room_of(module: str) -> str:
    rooms = [r for r, prefixes in ROOMS.items() if any(_matches(module, p) for p in prefixes)]
    assert len(rooms) == 1, f"{module}: in rooms {rooms} of {DESIGN.name} (expected one)"
    return rooms[0]


def allowed(src: str, dst: str) -> bool:
    """May module ``src`` import module ``dst``? Its own room, or along an edge: a room name,
    or ``room.sub`` for that module (and what is under it) of the room."""
    a, b = room_of(src), room_of(dst)
    if a == b:
        return True
    for edge in EDGES.get(a, ()):
        room, _, sub = edge.partition(".")
        if room == b and (not sub or _matches(dst, f"{ROOMS[b][0]}.{sub}")):
            return True
    return False


# ----------------------------------------------------------------------------- the source


@dataclass
class Imports:
    runtime: set[str] = field(default_factory=set)
    typing: set[str] = field(default_factory=set)  # under `if TYPE_CHECKING:`
    private: set[str] = field(default_factory=set)  # 'module.name' of private names used
    lines: dict[str, int] = field(default_factory=dict)


def _nodes(tree: ast.AST) -> Iterator[tuple[ast.AST, bool]]:
    """Every node, with whether it sits under ``if TYPE_CHECKING:``."""
    stack: list[tuple[ast.AST, bool]] = [(tree, False)]
    while stack:
        node, typing = stack.pop()
        yield node, typing
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                stack.extend((c, True) for c in child.body)
                stack.extend((c, typing) for c in child.orelse)
                continue
            stack.append((child, typing))


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _resolve(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if MODULES[module].name == "__init__.py" else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def _imports(module: str) -> Imports:
    tree = ast.parse(MODULES[module].read_text(), str(MODULES[module]))
    out = Imports()
    aliases: dict[str, str] = {}
    for node, typing in _nodes(tree):
        found: list[str] = []
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name in MODULES:
                    found.append(a.name)
                    aliases[a.asname or a.name] = a.name
        elif isinstance(node, ast.ImportFrom):
            src = _resolve(module, node)
            for a in node.names:
                sub = f"{src}.{a.name}"
                if sub in MODULES:
                    found.append(sub)
                    aliases[a.asname or a.name] = sub
                elif src in MODULES:
                    found.append(src)
                    if _private(a.name) and src != module:
                        out.private.add(sub)
        for dep in found:
            if dep != module:
                (out.typing if typing else out.runtime).add(dep)
                out.lines.setdefault(dep, getattr(node, "lineno", 0))
    for node, _ in _nodes(tree):  # ex._helper on an imported module
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in aliases and _private(node.attr)):
            out.private.add(f"{aliases[node.value.id]}.{node.attr}")
    out.typing -= out.runtime
    return out


IMPORTS = {m: _imports(m) for m in MODULES}
GRAPH = {m: imp.runtime for m, imp in IMPORTS.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), as sorted lists."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _violations(imports: dict[str, Imports]) -> list[str]:
    return sorted(f"{MODULES[m].relative_to(ROOT)}:{imp.lines[d]}: {room_of(m)} {m} imports "
                  f"{room_of(d)} {d}"
                  for m, imp in imports.items() for d in imp.runtime | imp.typing
                  if not allowed(m, d))


# ----------------------------------------------------------------------------- the checks


def test_the_walk_sees_the_package_and_its_edges() -> None:
    """The checks below mean something only if the walk finds the modules and their edges:
    a lazy import inside a function, a `from pkg import module`, a TYPE_CHECKING import."""
    assert {"robid_link.ident.fit.identify", "robid_link.drivers.file_share",
            "robid_link.fakes.plant", "robid_link.link.worker", "robid_link.jobs"} <= set(MODULES)
    assert "robid_link.ident.fit.design" in GRAPH["robid_link.ident.fit.identify"]
    assert "robid_link.ident.model.robot" in IMPORTS["robid_link.cli.analyse"].runtime  # lazy
    assert "robid_link.ident.excite.excitation" in GRAPH["robid_link.fakes.controller"]


def test_every_module_is_in_exactly_one_room_of_the_document() -> None:
    for module in MODULES:
        room_of(module)
    assert set(EDGES) == set(ROOMS), "every room of the rooms table has a row of edges"
    for room, edges in EDGES.items():
        for edge in edges:
            assert edge.partition(".")[0] in ROOMS, f"{room} → {edge}: no such room"


def test_imports_follow_the_edges_of_the_design() -> None:
    assert _violations(IMPORTS) == []


def test_a_forbidden_edge_is_caught() -> None:
    """The link importing the worker, and a fake importing a driver, are refused."""
    bad = {m: Imports() for m in ("robid_link.link.campaign", "robid_link.fakes.plant")}
    bad["robid_link.link.campaign"].typing.add("robid_link.ident.model.robot")
    bad["robid_link.fakes.plant"].runtime.add("robid_link.drivers.rapid")
    for imp in bad.values():
        imp.lines = dict.fromkeys(imp.runtime | imp.typing, 1)
    assert len(_violations(bad)) == 2
    assert allowed("robid_link.drivers.file_share", "robid_link.link.driver")
    assert not allowed("robid_link.drivers.file_share", "robid_link.link.campaign")


def test_no_import_cycle() -> None:
    assert _cycles(GRAPH) == []


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = dict(GRAPH)
    graph["robid_link.ident.model.robot"] = (GRAPH["robid_link.ident.model.robot"]
                                              | {"robid_link.ident.fit.identify"})
    assert any("robid_link.ident.model.robot" in c for c in _cycles(graph))


def test_no_private_name_imported_across_modules() -> None:
    used = sorted(f"{m} uses {p}" for m, imp in IMPORTS.items() for p in imp.private
                  if p.rpartition(".")[0] != m)
    assert used == []


@pytest.mark.parametrize("folder", sorted({p.parent for p in MODULES.values()}),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_no_package_folder_holds_more_than_twelve_modules(folder: Path) -> None:
    count = len(list(folder.glob("*.py")))
    assert count <= MAX_MODULES, f"{folder.relative_to(ROOT)}: {count} modules"


def test_every_test_file_has_one_kind_and_every_listed_kind_a_file() -> None:
    """Tests are sorted into unit / contract / e2e (``tests/conftest.py``): each file has one
    kind, and no pattern of the table is stale."""
    from tests.conftest import TEST_KINDS, kind_of

    files = sorted((ROOT / "tests").rglob("test_*.py"))
    kinds = {f: kind_of(f) for f in files}
    for kind, globs in TEST_KINDS.items():
        for glob in globs:
            assert any(f.relative_to(ROOT / "tests").match(glob) for f in files), glob
        assert kind in kinds.values()
    assert "unit" in kinds.values()
