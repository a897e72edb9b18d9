"""The packages' shape: no import cycle between modules, no module importing from a layer above its own, and the
plugin (hpgs_ns) never importing the lab (hpgs_lab), which imports only the plugin.

The import graph is read statically (every `import` statement, at module level or inside a function), as a
newcomer reading the code would follow it; a package's `__init__` importing its own submodules is not a cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Set

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "hpgs_ns"  # the plugin
LAB = REPO / "hpgs_lab"  # the benchmark lab


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def import_graph(packages=(PACKAGE, LAB)) -> Dict[str, Set[str]]:
    """module -> the modules of `packages` it imports (anywhere in its file)."""
    files = {module_name(p): p for package in packages for p in package.rglob("*.py")}
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
                # `from pkg import sub` imports the submodule when there is one (and pkg's __init__ only otherwise)
                subs = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in files]
                candidates = subs if len(subs) == len(node.names) else [base] + subs
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


def top_level_imports(path: Path) -> Set[str]:
    """The top-level packages a file imports, anywhere in it (absolute imports; relative ones stay in its package)."""
    found: Set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name.partition(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.add(node.module.partition(".")[0])
    return found


def test_the_plugin_never_imports_the_lab_and_the_lab_imports_only_the_plugin():
    """Arrows only lab -> plugin: no hpgs_ns module imports hpgs_lab, not even inside a function (the lab's
    `hpgs bench` reaches the plugin's `hpgs` through the `hpgs.commands` entry point), and of this repository's
    packages the lab imports only hpgs_ns."""
    graph = import_graph()
    assert graph and any(m.startswith("hpgs_lab.") for m in graph) and any(m.startswith("hpgs_ns.") for m in graph)
    plugin_to_lab = sorted(f"{a} imports {b}" for a, targets in graph.items() if a.split(".")[0] == "hpgs_ns"
                           for b in targets if b.split(".")[0] == "hpgs_lab")
    assert plugin_to_lab == []
    ours = {p.name for p in REPO.iterdir() if (p / "__init__.py").is_file()} | {"benchmarks", "tests", "scripts"}
    assert ours >= {"hpgs_ns", "hpgs_lab"}
    for package, allowed in ((PACKAGE, {"hpgs_ns"}), (LAB, {"hpgs_ns", "hpgs_lab"})):
        for path in package.rglob("*.py"):
            assert top_level_imports(path) & ours <= allowed, f"{path.relative_to(REPO)} imports {top_level_imports(path) & ours}"
    assert not (PACKAGE / "bench").exists()  # the lab's old home inside the plugin


def test_the_lab_check_sees_an_import_of_the_lab(tmp_path):
    plugin = tmp_path / "hpgs_ns"
    plugin.mkdir()
    (plugin / "cli.py").write_text("def bench():\n    from hpgs_lab.runs import Bench\n")
    assert top_level_imports(plugin / "cli.py") == {"hpgs_lab"}


# The package's layers, lowest first: a module imports only from its own layer or the ones below it. A module
# belongs to the longest prefix listed.
LAYERS = (
    ("utilities", ("hpgs_ns.errors", "hpgs_ns.atomic_write", "hpgs_ns.image_files", "hpgs_ns.metrics", "hpgs_ns.offline_weights",
                   "hpgs_ns.ns_train", "hpgs_ns.schedules")),
    ("rendering and scenes", ("hpgs_ns.cpu_raster", "hpgs_ns.render", "hpgs_ns.scenes", "hpgs_ns.dataparser")),
    ("preference model", ("hpgs_ns.preference",)),
    ("selectors", ("hpgs_ns.selectors",)),
    ("trainer strategies", ("hpgs_ns.strategies",)),
    ("round records", ("hpgs_ns.selection.records", "hpgs_ns.selection.schedule")),
    ("training parts", ("hpgs_ns.model", "hpgs_ns.datamanager", "hpgs_ns.viewer")),
    ("selection loop", ("hpgs_ns.selection",)),
    ("pipeline", ("hpgs_ns.pipeline", "hpgs_ns.compat")),
    ("trainer", ("hpgs_ns.trainer",)),
    ("method", ("hpgs_ns.method_config", "hpgs_ns.run_config")),
    ("commands", ("hpgs_ns", "hpgs_ns.cli", "hpgs_ns.demo", "hpgs_ns.suggest")),
    ("the lab", ("hpgs_lab",)),  # above the whole plugin: it may import any of it, nothing imports it
)


def layer(module: str) -> int:
    matches = [(len(prefix), rank) for rank, (_, prefixes) in enumerate(LAYERS) for prefix in prefixes
               if module == prefix or module.startswith(prefix + ".")]
    assert matches, f"{module} is in no layer of LAYERS"
    return max(matches)[1]


def test_no_module_imports_one_meant_to_sit_above_it():
    graph = import_graph()
    upward = sorted(f"{a} ({LAYERS[layer(a)][0]}) imports {b} ({LAYERS[layer(b)][0]})"
                    for a, targets in graph.items() for b in targets if layer(b) > layer(a))
    assert upward == []


def test_the_layer_check_sees_an_upward_import():
    assert layer("hpgs_ns.selection.records") < layer("hpgs_ns.datamanager") < layer("hpgs_ns.selection.rounds")
    assert layer("hpgs_ns.render.pair_render") < layer("hpgs_ns.selectors.fisher") < layer("hpgs_lab.runs")
