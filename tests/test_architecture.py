"""House rules for imports inside ``pimbrl``, checked on the source with ``ast`` (nothing is imported).

Layering, top to bottom (a module may import its own group and the groups below it, never above)::

    cli -> experiments -> training -> control -> agents | models -> simulate, pimbrl/__init__ -> systems -> envs
        -> plotting -> physics -> buffers, spaces, config, fileio

``agents`` and ``models`` are independent: neither imports the other. ``simulate`` and ``plotting`` are
utilities: ``simulate`` runs an environment, ``plotting`` draws arrays and may use nothing above
``physics``. ``control`` (feedback, MPC, DPC) drives the models' differentiable schemes and the systems'
declarations. The root package ``pimbrl/__init__.py`` registers the environments and holds ``__version__``.

Every ``import`` and ``from ... import`` counts, at module level and inside functions, absolute and
relative, except those under ``if TYPE_CHECKING:``: they never run, so they can neither form an import
cycle at run time nor make a module depend on another when it runs. (import-linter's contracts in
pyproject.toml check the same rules with ``exclude_type_checking_imports``.)
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
ROOT_PACKAGE = "pimbrl"

#: rank of each group (the first dotted component below ``pimbrl``); a module may import ranks <= its own
RANKS: dict[str, float] = {
    "buffers": 0,
    "spaces": 0,
    "config": 0,
    "fileio": 0,
    "physics": 1,
    "plotting": 2,
    "envs": 3,
    # the systems: declared from physics and envs; everything above reads their declarations
    "systems": 3.5,
    "simulate": 4,
    "agents": 5,
    "models": 5,
    # control that knows the physics: runs the systems' equations through the models' schemes
    "control": 5.5,
    "training": 6,
    "experiments": 7,
    "cli": 8,
    # the root package only registers the environments (and holds __version__): it may import envs and
    # below, and the layers above envs may import it
    "": 4,
    "__main__": 9,  # ``python -m pimbrl``, if one is added: the top, like cli
}
#: groups of equal rank that must not import each other
INDEPENDENT = [{"agents", "models"}]


@dataclass(frozen=True)
class Import:
    """One import statement's edge: ``importer`` imports ``imported`` at ``path:line``."""

    importer: str
    imported: str
    path: str  # relative to the repository root, e.g. ``src/pimbrl/x.py``
    line: int
    text: str

    def where(self) -> str:
        """``src/pimbrl/x.py:12: from .y import z``."""
        return f"{self.path}:{self.line}: {self.text}"


def _module_name(path: Path, src: Path) -> str:
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of the nodes inside the body of an ``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``)."""
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            test = node.test
            name = test.id if isinstance(test, ast.Name) else test.attr if isinstance(test, ast.Attribute) else None
            if name == "TYPE_CHECKING":
                for stmt in node.body:
                    skipped.update(id(n) for n in ast.walk(stmt))
    return skipped


def _segment(lines: list[str], node: ast.stmt) -> str:
    """The source text of an import statement, from the file's lines split once."""
    first, last = node.lineno - 1, (node.end_lineno or node.lineno) - 1
    start, end = node.col_offset, node.end_col_offset  # offsets in UTF-8 bytes, as ast gives them
    cut = lambda i, a, b: lines[i].encode()[a:b].decode()
    if first == last:
        return cut(first, start, end)
    return "\n".join([cut(first, start, None), *lines[first + 1 : last], cut(last, None, end)])


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` statement imports from."""
    if node.level == 0:
        return node.module or ""
    package = module.split(".") if is_package else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def build_graph(src: Path = SRC, root: str = ROOT_PACKAGE) -> tuple[set[str], list[Import]]:
    """All modules of package ``root`` under ``src`` and every import between two of them."""
    files = sorted((src / root).rglob("*.py"))
    modules = {_module_name(f, src) for f in files}
    edges: list[Import] = []
    for path in files:
        module = _module_name(path, src)
        source = path.read_text()
        lines = source.splitlines()  # once per file: ast.get_source_segment splits the whole file on every call
        tree = ast.parse(source, filename=str(path))
        skipped = _type_checking_nodes(tree)
        for node in ast.walk(tree):
            if id(node) in skipped:
                continue
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(module, path.name == "__init__.py", node)
                for alias in node.names:
                    # ``from pkg import sub`` imports the submodule ``pkg.sub`` when there is one
                    sub = f"{base}.{alias.name}"
                    targets.append(sub if sub in modules else base)
            else:
                continue
            text = _segment(lines, node)
            for target in dict.fromkeys(targets):
                # ``import pimbrl.a.b`` names a module; keep the longest known prefix of anything else
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != module:
                    shown = path.relative_to(src.parent).as_posix()
                    edges.append(Import(module, target, shown, node.lineno, " ".join(text.split())))
    return modules, edges


def _group(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def find_cycles(modules: set[str], edges: list[Import]) -> list[list[Import]]:
    """One concrete cycle (as its list of imports) per strongly connected component of the import graph."""
    succ: dict[str, dict[str, Import]] = {m: {} for m in modules}
    for e in edges:
        succ[e.importer].setdefault(e.imported, e)
    # Tarjan's algorithm, iterative
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[list[str]] = []
    counter = 0
    for start in sorted(modules):
        if start in index:
            continue
        work = [(start, iter(sorted(succ[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(succ[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    component.append(m)
                    if m == node:
                        break
                if len(component) > 1:
                    components.append(sorted(component))
    cycles = []
    for component in components:
        members = set(component)
        # shortest path back to the first member, inside the component (breadth-first)
        first = component[0]
        parent: dict[str, Import] = {}
        frontier = [first]
        found: Import | None = None
        while frontier and found is None:
            nxt = []
            for m in frontier:
                for target, e in sorted(succ[m].items()):
                    if target == first:
                        found = e
                        break
                    if target in members and target not in parent and target != first:
                        parent[target] = e
                        nxt.append(target)
                if found is not None:
                    break
            frontier = nxt
        assert found is not None
        path = [found]
        while path[0].importer != first:
            path.insert(0, parent[path[0].importer])
        cycles.append(path)
    return cycles


def layer_violations(edges: list[Import]) -> list[Import]:
    """Imports from a group to a higher-ranked group, or between two independent groups."""
    bad = []
    for e in edges:
        src, dst = _group(e.importer), _group(e.imported)
        if src == dst:
            continue
        if src not in RANKS or dst not in RANKS:
            raise AssertionError(f"{e.where()}: group {src if src not in RANKS else dst!r} has no rank in RANKS; add it")
        if RANKS[dst] > RANKS[src] or any({src, dst} <= group for group in INDEPENDENT):
            bad.append(e)
    return bad


@pytest.fixture(scope="module")
def graph() -> tuple[set[str], list[Import]]:
    return build_graph()


def test_the_graph_sees_every_kind_of_import(tmp_path: Path) -> None:
    files = {
        "pkg/__init__.py": "from .a import x\n",
        "pkg/a.py": "import os\nimport pkg.sub.c\nx = 1\n",
        "pkg/sub/__init__.py": "from . import c\nfrom .. import a\n",
        "pkg/sub/b.py": (
            "from typing import TYPE_CHECKING\n"
            "from ..a import x\n"
            "if TYPE_CHECKING:\n    from pkg.sub import c\n"
            "def f():\n    from pkg import sub\n    return sub\n"
        ),
        "pkg/sub/c.py": "class C:\n    def m(self):\n        from .b import f\n        return f\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    modules, edges = build_graph(tmp_path, "pkg")
    assert modules == {"pkg", "pkg.a", "pkg.sub", "pkg.sub.b", "pkg.sub.c"}
    assert sorted((e.importer, e.imported, e.line) for e in edges) == [
        ("pkg", "pkg.a", 1),  # relative, from a package __init__
        ("pkg.a", "pkg.sub.c", 2),  # absolute ``import a.b.c``
        ("pkg.sub", "pkg.a", 2),  # ``from .. import module``
        ("pkg.sub", "pkg.sub.c", 1),  # ``from . import module``
        ("pkg.sub.b", "pkg.a", 2),  # ``from ..a import name``
        ("pkg.sub.b", "pkg.sub", 6),  # in a function; the TYPE_CHECKING import of line 4 is left out
        ("pkg.sub.c", "pkg.sub.b", 3),  # in a method
    ]
    assert edges[0].where() == f"{tmp_path.name}/pkg/__init__.py:1: from .a import x"


def test_the_real_graph_is_found(graph: tuple[set[str], list[Import]]) -> None:
    modules, edges = graph
    assert {"pimbrl", "pimbrl.physics.base", "pimbrl.systems.burgers"} <= modules
    pairs = {(e.importer, e.imported) for e in edges}
    assert ("pimbrl.physics.pde", "pimbrl.physics.base") in pairs
    assert ("pimbrl.systems.burgers", "pimbrl.physics.base") in pairs
    assert ("pimbrl", "pimbrl.systems.registry") in pairs


def test_cycle_finder_and_layer_rule_catch_what_they_should() -> None:
    def imp(a: str, b: str) -> Import:
        return Import(a, b, "src/pimbrl/x.py", 1, f"import {b}")

    modules = {"pimbrl.a", "pimbrl.b", "pimbrl.c", "pimbrl.d"}
    cycles = find_cycles(
        modules,
        [imp("pimbrl.a", "pimbrl.b"), imp("pimbrl.b", "pimbrl.c"), imp("pimbrl.c", "pimbrl.a"), imp("pimbrl.c", "pimbrl.d")],
    )
    assert [[e.importer for e in c] for c in cycles] == [["pimbrl.a", "pimbrl.b", "pimbrl.c"]]
    assert find_cycles(modules, [imp("pimbrl.a", "pimbrl.b"), imp("pimbrl.b", "pimbrl.c")]) == []
    assert layer_violations([imp("pimbrl.systems.ks", "pimbrl.physics")]) == []
    assert len(layer_violations([imp("pimbrl.physics.pde", "pimbrl.envs")])) == 1
    assert len(layer_violations([imp("pimbrl.envs.task", "pimbrl.systems")])) == 1
    assert len(layer_violations([imp("pimbrl.agents.td3", "pimbrl.models.networks")])) == 1


def test_no_import_cycles(graph: tuple[set[str], list[Import]]) -> None:
    modules, edges = graph
    cycles = find_cycles(modules, edges)
    report = "\n\n".join(
        " -> ".join([*(e.importer for e in c), c[0].importer]) + "\n" + "\n".join(f"    {e.where()}" for e in c) for c in cycles
    )
    assert not cycles, f"{len(cycles)} import cycle(s) between pimbrl modules:\n\n{report}"


def test_no_import_from_a_lower_layer_to_a_higher_one(graph: tuple[set[str], list[Import]]) -> None:
    _, edges = graph
    bad = layer_violations(edges)
    report = "\n".join(f"    {e.where()}    ({_group(e.importer)} -> {_group(e.imported)})" for e in bad)
    assert not bad, f"{len(bad)} import(s) against the layering (see the module docstring):\n{report}"
