"""Which of the plugin's source files can change a run's numbers, for tools that record what made a result.

`code_files()` is every module of the package but those listed in `NOT_CODE`: the command lines, the viewer,
the preference-model tools, `suggest`, and the selectors, whose files count only for that selector's runs (its
config's `code_files`). A new module counts until it is listed there, so a hash of these files errs toward
calling a result stale, never toward mixing results of other code.
"""

from __future__ import annotations

from pathlib import Path
from typing import Tuple

PACKAGE = Path(__file__).resolve().parent

# Modules (relative to the package; a name ending in "/" is a folder) that cannot change a run's numbers.
NOT_CODE: Tuple[str, ...] = (
    "__init__.py", "atomic_write.py", "cli.py", "compat.py", "demo.py", "errors.py", "ns_train.py", "provenance.py",
    "run_config.py", "viewer.py",
    "preference/", "render/__init__.py", "render/coverage.py", "scenes/__init__.py", "selection/__init__.py",
    "selection/candidate_log.py", "selection/log.py", "selectors/", "suggest/",
)
# The selectors/ modules every selector runs through: they count for every run.
SHARED_SELECTOR_FILES: Tuple[str, ...] = ("selectors/base.py", "selectors/registry.py")


def is_code(rel: str) -> bool:
    """Whether the module at `rel` ("/"-separated, relative to the package) can change any run's numbers."""
    if rel in SHARED_SELECTOR_FILES:
        return True
    return not any(rel == name or (name.endswith("/") and rel.startswith(name)) for name in NOT_CODE)


def code_files(package: Path = PACKAGE) -> Tuple[str, ...]:
    """The modules of the plugin tree at `package` (relative, "/"-separated, sorted) whose change can change any
    run's numbers."""
    package = Path(package)
    rels = sorted(path.relative_to(package).as_posix() for path in package.rglob("*.py"))
    return tuple(rel for rel in rels if is_code(rel))
