"""The package's shape: no import cycle between modules, and old module paths still import.

The import graph is read statically (every `import` statement, at module level or inside a function), as a
newcomer reading the code would follow it; a package's `__init__` importing its own submodules is not a cycle.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path
from typing import Dict, List, Set

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "hpgs_ns"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def import_graph() -> Dict[str, Set[str]]:
    """module -> the package modules it imports (anywhere in its file)."""
    files = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: Dict[str, Set[str]] = {}
    for name, path in files.items():
        is_package = path.name == "__init__.py"
        targets: Set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                candidates = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = name.split(".") if is_package else name.split(".")[:-1]
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                # `from pkg import sub` imports the submodule when there is one
                candidates = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for c in candidates:
                # the longest known module the import names (a.b.c -> a.b when c is a function)
                while c and c not in files:
                    c = c.rpartition(".")[0]
                if c and c != name:
                    targets.add(c)
        graph[name] = targets
    return graph


def cycles(graph: Dict[str, Set[str]]) -> List[List[str]]:
    """Every strongly connected component of more than one module (Tarjan), ignoring package -> own submodule."""

    def own_submodule(a: str, b: str) -> bool:
        return b.startswith(a + ".") or a.startswith(b + ".")

    edges = {a: {b for b in bs if not own_submodule(a, b)} for a, bs in graph.items()}
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
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

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_the_graph_reader_sees_a_cycle_when_there_is_one():
    assert cycles({"p.a": {"p.b"}, "p.b": {"p.c"}, "p.c": {"p.a"}, "p.d": {"p.a"}}) == [["p.a", "p.b", "p.c"]]
    assert cycles({"p": {"p.a"}, "p.a": {"p"}}) == []  # a package and its own submodule


def test_no_import_cycle_between_modules():
    graph = import_graph()
    assert cycles(graph) == []


def test_the_datamanager_does_not_reach_up_to_rounds_or_the_benchmark():
    graph = import_graph()
    assert not {"hpgs_ns.rounds", "hpgs_ns.pipeline"} & graph["hpgs_ns.datamanager"]
    for module, targets in graph.items():
        if not module.startswith("hpgs_ns.bench"):
            assert not {t for t in targets if t.startswith("hpgs_ns.bench")}, module


@pytest.mark.parametrize("old, new", sorted(importlib.import_module("hpgs_ns").MOVED_MODULES.items()))
def test_moved_modules_still_import_under_their_old_names(old, new):
    assert importlib.import_module(old) is importlib.import_module(new)
