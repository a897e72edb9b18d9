"""The plugin's shape: no import cycle between hpgs_ns's modules, no module importing from a layer above its own,
and neither the plugin nor its tests (tests/plugin) importing the lab (hpgs_lab) or the scripts in benchmarks/.
(The lab's own shape: tests/lab/test_lab_architecture.py.)

The import graph is read statically (every `import` statement, at module level or inside a function), as a
newcomer reading the code would follow it; a package's `__init__` importing its own submodules is not a cycle.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import Dict, Iterable, List, Set, Tuple

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "hpgs_ns"  # the plugin
PLUGIN_TESTS = REPO / "tests" / "plugin"
LAB = ("hpgs_lab", "benchmarks")  # the lab's package and its scripts' folder: nothing of the plugin's imports them


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def import_graph(packages=(PACKAGE,)) -> Dict[str, Set[str]]:
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


IMPORTERS = {"import_module", "__import__", "find_spec", "run_module"}  # importlib.*, builtins, runpy: a module by name
# a string that names the lab's folders as a path or a module ("benchmarks", REPO / "hpgs_lab", "hpgs_lab.cli:bench"),
# not prose that mentions them (a docstring saying which benchmark measures a speed)
LAB_PATH = re.compile(r"^(hpgs_lab|benchmarks)([./:\\][^\s]*)?$")


def imports_in(path: Path) -> List[Tuple[int, str]]:
    """(line, module) for every module a file imports by name, anywhere in it: `import` and `from ... import`
    statements (absolute ones; relative ones stay in its package), at module level or inside a function, the
    string literal passed to `importlib.import_module`, `__import__`, `importlib.util.find_spec` or
    `runpy.run_module`, and the imports of a string literal that is Python code (a `python -c` probe)."""
    return code_imports(path.read_text(), str(path))


def code_imports(source: str, filename: str, line: int = 0) -> List[Tuple[int, str]]:
    found: List[Tuple[int, str]] = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            found += [(line + node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.append((line + node.lineno, node.module))
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if name in IMPORTERS and isinstance(node.args[0].value, str):
                found.append((line + node.lineno, node.args[0].value))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and "import " in node.value:
            try:
                found += code_imports(node.value, filename, line + node.lineno - 1)
            except SyntaxError:  # prose, or a template
                pass
    return found


def top_level_imports(path: Path) -> Set[str]:
    """The top-level packages a file imports, anywhere in it (`imports_in`)."""
    return {module.partition(".")[0] for _, module in imports_in(path)}


def shown(path: Path) -> str:
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def lab_imports(paths: Iterable[Path], script_names: Set[str] = frozenset()) -> List[str]:
    """`file:line imports X` for every import of hpgs_lab or benchmarks in `paths` (and of a module in
    `script_names`: a benchmarks/ script imported after putting its folder on sys.path)."""
    return sorted(f"{shown(path)}:{line} imports {module}" for path in paths
                  for line, module in imports_in(path) if module.partition(".")[0] in set(LAB) | script_names)


def lab_paths(path: Path) -> List[str]:
    """`file:line names X` for every string literal naming hpgs_lab or benchmarks as a path or module (what
    `sys.path.insert`, `runpy.run_path`, `subprocess.run` or `importlib.util.spec_from_file_location` would be
    handed to reach them)."""
    return sorted(f"{shown(path)}:{node.lineno} names {node.value!r}"
                  for node in ast.walk(ast.parse(path.read_text(), str(path)))
                  if isinstance(node, ast.Constant) and isinstance(node.value, str) and LAB_PATH.match(node.value))


def test_the_plugin_never_imports_the_lab_nor_the_benchmarks():
    """Arrows only lab -> plugin: no hpgs_ns module imports hpgs_lab or benchmarks/, not even inside a function or
    by name through importlib (the lab's `hpgs bench` reaches the plugin's `hpgs` through the `hpgs.commands` entry
    point)."""
    files = sorted(PACKAGE.rglob("*.py"))
    assert len(files) > 20
    assert lab_imports(files) == []
    ours = {p.name for p in REPO.iterdir() if (p / "__init__.py").is_file()} | {"benchmarks", "tests", "scripts"}
    assert "hpgs_ns" in ours
    outside = sorted(f"{path.relative_to(REPO)} imports {top_level_imports(path) & ours - {'hpgs_ns'}}"
                     for path in files if top_level_imports(path) & ours - {"hpgs_ns"})
    assert outside == []
    assert not (PACKAGE / "bench").exists()  # the lab's old home inside the plugin


def test_the_plugin_tests_never_import_the_lab_nor_the_benchmarks():
    """tests/plugin tests the plugin alone (the lab's tests, and tests of benchmarks/ scripts, are in tests/lab): no
    file there imports hpgs_lab or a benchmarks/ script, nor names either folder as a path to reach one."""
    files = sorted(set(PLUGIN_TESTS.rglob("*.py")) - {Path(__file__).resolve()})  # this file names what it looks for
    scripts = {p.stem for p in (REPO / "benchmarks").glob("*.py")}
    assert len(files) > 20
    assert lab_imports(files, scripts) == []
    assert [hit for path in files for hit in lab_paths(path)] == []


def test_the_lab_check_sees_an_import_of_the_lab(tmp_path):
    plugin = tmp_path / "hpgs_ns"
    plugin.mkdir()
    (plugin / "cli.py").write_text("import importlib\n\n\ndef bench():\n    from hpgs_lab.runs import Bench\n")
    (plugin / "by_name.py").write_text("import importlib\nrunner = importlib.import_module('hpgs_lab.cli')\n")
    (plugin / "script.py").write_text("import sys\nsys.path.insert(0, str(REPO / 'benchmarks'))\nimport suggest_check\n")
    assert top_level_imports(plugin / "cli.py") == {"hpgs_lab", "importlib"}
    assert top_level_imports(plugin / "by_name.py") == {"hpgs_lab", "importlib"}
    found = lab_imports([plugin / "cli.py", plugin / "by_name.py", plugin / "script.py"], {"suggest_check"})
    assert [hit.rpartition(":")[2] for hit in found] == ["2 imports hpgs_lab.cli", "5 imports hpgs_lab.runs",
                                                         "3 imports suggest_check"]
    assert [hit.rpartition(":")[2] for hit in lab_paths(plugin / "script.py")] == ["2 names 'benchmarks'"]
    (plugin / "prose.py").write_text('"""How fast: benchmarks/help_time.py measures it; hpgs_lab reads it."""\n')
    assert lab_paths(plugin / "prose.py") == [] and lab_imports([plugin / "prose.py"]) == []
    (plugin / "probe.py").write_text('import subprocess\n\nPROBE = """\nimport json\nfrom hpgs_lab.protocols import row_order\n"""\n')
    assert [hit.rpartition(":")[2] for hit in lab_imports([plugin / "probe.py"])] == ["5 imports hpgs_lab.protocols"]


# The package's layers, lowest first: a module imports only from its own layer or the ones below it. A module
# belongs to the longest prefix listed.
LAYERS = (
    ("utilities", ("hpgs_ns.errors", "hpgs_ns.atomic_write", "hpgs_ns.image_files", "hpgs_ns.metrics", "hpgs_ns.offline_weights",
                   "hpgs_ns.ns_train", "hpgs_ns.schedules", "hpgs_ns.resume_keys", "hpgs_ns.provenance")),
    ("rendering and scenes", ("hpgs_ns.cpu_raster", "hpgs_ns.render", "hpgs_ns.scenes", "hpgs_ns.dataparser")),
    ("preference model", ("hpgs_ns.preference",)),
    ("selectors", ("hpgs_ns.selectors",)),
    ("trainer strategies", ("hpgs_ns.strategies",)),
    # the migrations of old configs and checkpoints: every config class reads its old files through it
    ("round records and compatibility", ("hpgs_ns.selection.records", "hpgs_ns.selection.schedule", "hpgs_ns.compat")),
    ("training parts", ("hpgs_ns.model", "hpgs_ns.datamanager", "hpgs_ns.viewer")),
    ("selection loop", ("hpgs_ns.selection",)),
    ("pipeline", ("hpgs_ns.pipeline",)),
    ("trainer", ("hpgs_ns.trainer",)),
    ("method", ("hpgs_ns.method_config", "hpgs_ns.run_config")),
    ("commands", ("hpgs_ns", "hpgs_ns.cli", "hpgs_ns.demo", "hpgs_ns.suggest")),
)  # the lab (hpgs_lab) sits above them all: it may import any of it, nothing of it imports the lab


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
    assert layer("hpgs_ns.render.pair_render") < layer("hpgs_ns.selectors.fisher") < layer("hpgs_ns.cli")
