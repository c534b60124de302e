"""The import graph of diffsmf has no cycles, and every import points down the floors.

Every ``import`` of a diffsmf module counts, at module level or inside a function: an import
moved into a function to dodge a cycle still ties the two modules together. Read with ``ast``
(nothing is imported), so the test takes well under a second.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Cycles still to be broken, each as the set of modules of one strongly connected component
#: (none: the set conversions are registered in `diffsmf.sets.conversions` and the built-in
#: systems in `diffsmf.systems.registry`). The test fails on any cycle that is not a subset of
#: an entry.
KNOWN_CYCLES: list[frozenset[str]] = []


def modules(root: Path, package: str) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of ``package`` under ``root``."""
    out = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(name: str, mods: dict[str, Path]) -> str | None:
    """The module of ``mods`` that an import of ``name`` loads (its longest known prefix)."""
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """``{module: modules of the package it imports}`` (``from pkg import sub`` -> ``pkg.sub``)."""
    mods = modules(root, package)
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative import
                    parent = base[: len(base) - node.level + 1]
                    src = ".".join(parent + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                found = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src
                         for a in node.names]
            else:
                continue
            targets.update(t for t in (_resolve(f, mods) for f in found) if t and t != name)
        graph[name] = targets
    return graph


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = set()
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.add(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(frozenset(comp))
    return found


def test_the_checker_finds_a_cycle_through_a_function_level_import(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from pkg.sub import c\n")
    (pkg / "a.py").write_text("from pkg import b\n")
    (pkg / "b.py").write_text("def f():\n    from . import a\n")
    (pkg / "sub" / "c.py").write_text("import pkg.a\n")
    graph = import_graph(tmp_path, "pkg")
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}
    assert graph["pkg.sub"] == {"pkg.sub.c"} and graph["pkg.sub.c"] == {"pkg.a"}
    assert cycles(graph) == [frozenset({"pkg.a", "pkg.b"})]


#: The floors of diffsmf, bottom up (``docs/design.md`` draws them). A module may import
#: modules of its own floor and of the floors below it; an import that runs up fails
#: `test_every_import_points_down`. ``diffsmf`` is the package's facade (``import diffsmf as
#: ds``), which only the command line sits above.
FLOORS: list[tuple[str, ...]] = [
    ("utils",),
    ("linalg",),
    ("convex",),
    ("interval",),
    ("sets",),
    ("linearize",),
    ("systems",),
    ("filters", "pwl"),
    ("tuning", "observers", "tightness"),
    ("audit", "plot"),
    ("comparison",),
    ("",),  # diffsmf/__init__.py
    ("cli", "__main__"),
]


def floor_of(module: str) -> int:
    """The floor of ``module`` (``diffsmf.sets.zonotope`` -> the floor of ``sets``)."""
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else ""
    for i, names in enumerate(FLOORS):
        if top in names:
            return i
    raise AssertionError(f"{module} is on no floor: add {top!r} to FLOORS")


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """Every import of ``graph`` whose target stands on a higher floor than its importer."""
    return [f"{m} -> {t}" for m, targets in sorted(graph.items()) for t in sorted(targets)
            if floor_of(t) > floor_of(m)]


def test_the_checker_finds_an_import_that_runs_up(tmp_path):
    pkg = tmp_path / "diffsmf"
    (pkg / "sets").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sets" / "__init__.py").write_text("")
    (pkg / "utils.py").write_text("def f():\n    from diffsmf.sets import zono\n")
    (pkg / "sets" / "zono.py").write_text("from diffsmf import utils\n")
    assert upward_imports(import_graph(tmp_path, "diffsmf")) == [
        "diffsmf.utils -> diffsmf.sets.zono"]


def test_every_import_points_down():
    up = upward_imports(import_graph(ROOT, "diffsmf"))
    assert up == [], f"imports that run up the floors of FLOORS: {up}"


def test_diffsmf_has_no_import_cycles_but_the_known_ones():
    graph = import_graph(ROOT, "diffsmf")
    assert {"diffsmf.cli", "diffsmf.tuning.losses", "diffsmf.comparison"} <= set(graph)
    new = [sorted(c) for c in cycles(graph) if not any(c <= known for known in KNOWN_CYCLES)]
    assert new == [], f"import cycles in diffsmf: {new}"
