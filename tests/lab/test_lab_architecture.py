"""The lab's shape: of this repository's packages hpgs_lab imports only the plugin (hpgs_ns) and itself, and no
import cycle runs between its modules. (The plugin's side, that nothing of it imports the lab:
tests/plugin/test_architecture.py.)

Read statically, every `import` statement at module level or inside a function; a package's `__init__` importing
its own submodules is not a cycle.
"""

from __future__ import annotations

import ast
from graphlib import CycleError, TopologicalSorter
from pathlib import Path
from typing import Dict, Set

from conftest import REPO

LAB = REPO / "hpgs_lab"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(path: Path, name: str, modules: Set[str] = frozenset()) -> Set[str]:
    """The absolute names a module imports, anywhere in its file (relative imports resolved against its package).
    `from a import b` names `a.b` where that is one of `modules`, and `a` itself only where some name is not."""
    found: Set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                base = ".".join(anchor[: len(anchor) - (node.level - 1)] + ([base] if base else []))
            subs = {f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in modules}
            found |= subs if len(subs) == len(node.names) else subs | {base}
    return found


def lab_graph() -> Dict[str, Set[str]]:
    """hpgs_lab module -> the hpgs_lab modules it imports, without a package's own submodules."""
    files = {module_name(p): p for p in LAB.rglob("*.py")}
    graph: Dict[str, Set[str]] = {}
    for name, path in files.items():
        targets = set()
        for target in imported(path, name, set(files)):
            while target and target not in files:  # the longest module the import names (a.b.c -> a.b, c a function)
                target = target.rpartition(".")[0]
            if target and target != name and not (target.startswith(name + ".") or name.startswith(target + ".")):
                targets.add(target)
        graph[name] = targets
    return graph


def test_the_lab_imports_only_the_plugin_and_itself():
    ours = {p.name for p in REPO.iterdir() if (p / "__init__.py").is_file()} | {"benchmarks", "tests", "scripts"}
    assert ours >= {"hpgs_ns", "hpgs_lab"}
    wrong = {}
    for path in sorted(LAB.rglob("*.py")):
        tops = {n.partition(".")[0] for n in imported(path, module_name(path)) if n}
        if tops & ours - {"hpgs_ns", "hpgs_lab"}:
            wrong[str(path.relative_to(REPO))] = sorted(tops & ours - {"hpgs_ns", "hpgs_lab"})
    assert wrong == {}


def test_no_import_cycle_between_the_labs_modules():
    graph = lab_graph()
    assert len(graph) > 10 and any(graph.values())
    try:
        TopologicalSorter(graph).prepare()
    except CycleError as err:
        raise AssertionError(f"import cycle: {' -> '.join(err.args[1])}") from None


def test_the_cycle_check_sees_a_cycle():
    try:
        TopologicalSorter({"a": {"b"}, "b": {"a"}}).prepare()
    except CycleError as err:
        assert set(err.args[1]) == {"a", "b"}
    else:
        raise AssertionError("no cycle seen")
