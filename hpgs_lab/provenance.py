"""What made a benchmark run's numbers: the code, the preference model, every selector option.

Each run records them (`provenance` in its JSON), and the settings a resumed sweep compares include them, so a
results folder never mixes runs made by other code or another model without saying so.

"The code" is a hash of the plugin's source files that can move a run's numbers: the training path (model,
datamanager, dataparser, rounds, trainer, rasterizers, ...) and the run's own selector. Files that cannot (the
viewer, the CLIs, other selectors; and this lab, which only launches and reports runs) are left out, so that a sweep
built over several sessions can resume across commits that only touch those. The plugin declares which are which
(`hpgs_ns.provenance.code_files`). The git commit is recorded beside it, for reading.
"""

from __future__ import annotations

import ast
import dataclasses
import hashlib
import io
import os
import subprocess
import threading
import tokenize
from pathlib import Path
from typing import Dict, List, Optional

import hpgs_ns
from hpgs_lab.names import REFERENCES
from hpgs_ns.provenance import code_files

PACKAGE = Path(hpgs_ns.__file__).resolve().parent  # the plugin's tree: the code that makes a run's numbers
INSTALLED = PACKAGE  # where the plugin's modules are imported from (PACKAGE is the tree hashed)
# `hpgs bench --executor local` builds run records in threads; CPython 3.11's ast module keeps its recursion
# depth in shared state, so two threads in `ast.parse` at once can raise "AST constructor recursion depth
# mismatch" (python/cpython#106905). Parsing here is milliseconds: one thread at a time.
PARSE_LOCK = threading.RLock()


def selector_files(selector: str) -> List[Path]:
    """The files that can move a selector's numbers: its config's module and the `code_files` its config names
    (relative to this package), for built-in selectors and those of other packages alike."""
    import inspect

    from hpgs_ns.selectors.registry import selector_class

    config = selector_class(selector)
    module = Path(inspect.getfile(config)).resolve()
    if module.is_relative_to(INSTALLED):  # a built-in selector: its file in the tree being hashed
        module = PACKAGE / module.relative_to(INSTALLED)
    return [module] + [PACKAGE / rel for rel in config.code_files]


def code_hash(selector: Optional[str]) -> str:
    """sha256 of the plugin's code files (`hpgs_ns.provenance.code_files`, in the tree at PACKAGE) and the files of
    `selector` (a registered name; None for reference rows), each as `code_text` gives it: an edit to a comment or a
    docstring does not make a sweep's finished runs look stale."""
    files = {rel: PACKAGE / rel for rel in code_files(PACKAGE)}
    if selector is not None:
        for path in selector_files(selector):
            files[path.relative_to(PACKAGE).as_posix() if path.is_relative_to(PACKAGE) else path.name] = path
    digest = hashlib.sha256()
    for rel in sorted(files):
        path = files[rel]
        digest.update(rel.encode() + b"\0" + (code_text(path).encode() if path.is_file() else b"<missing>") + b"\0")
    return digest.hexdigest()[:16]


def code_text(path: Path) -> str:
    """A Python file's text without comments, docstrings (any string statement: the options' field docs too) and
    blank lines. Positions come from `tokenize` and `ast`, which read the same on every Python 3 version, so a GPU
    machine's Python and this one agree. A file that does not parse is taken whole."""
    text = Path(path).read_text(encoding="utf-8", errors="surrogateescape")
    try:
        with PARSE_LOCK:
            tree = ast.parse(text)
        tokens = list(tokenize.generate_tokens(io.StringIO(text).readline))
    except (SyntaxError, ValueError, tokenize.TokenError):
        return text
    lines = text.splitlines()

    def column(row: int, byte_offset: int) -> int:  # ast counts UTF-8 bytes, tokenize characters
        return len(lines[row - 1].encode("utf-8", "surrogateescape")[:byte_offset].decode("utf-8", "surrogateescape"))

    cuts = [(t.start, t.end) for t in tokens if t.type == tokenize.COMMENT]
    cuts += [((n.lineno, column(n.lineno, n.col_offset)), (n.end_lineno, column(n.end_lineno, n.end_col_offset)))
             for n in ast.walk(tree)
             if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant) and isinstance(n.value.value, str)]
    for (row, col), (end_row, end_col) in sorted(cuts, reverse=True):  # from the end: earlier positions hold
        lines[row - 1:end_row] = [lines[row - 1][:col] + lines[end_row - 1][end_col:]]
    return "\n".join(line.rstrip() for line in lines if line.strip())


def file_hash(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def git_commit() -> Optional[str]:
    """The checkout's commit (with `+dirty` when hpgs_ns/ has uncommitted changes), $HPGS_GIT_COMMIT where there
    is no git (a copied tree), else None."""
    try:
        out = subprocess.run(["git", "-C", str(PACKAGE), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if out.returncode == 0:
            dirty = subprocess.run(["git", "-C", str(PACKAGE), "diff", "--quiet", "HEAD", "--", "."], timeout=10).returncode
            return out.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return os.environ.get("HPGS_GIT_COMMIT") or None


def selector_options(selector: str, extra_args: List[str]) -> Optional[Dict]:
    """Every option of `selector` as the run will use it: its defaults, with `--pipeline.selection.<selector>.*`
    flags of `extra_args` applied (or their old spelling `--pipeline.datamanager.<selector>.*`; parsed by tyro, as
    ns-train does). None for the reference rows."""
    from hpgs_ns.selectors.registry import selector_config

    if selector in REFERENCES:  # no selector
        return None
    config = selector_config(selector)
    prefixes = tuple(f"--pipeline.{group}.{selector}." for group in ("selection", "datamanager"))
    own: List[str] = []
    for i, arg in enumerate(extra_args):
        prefix = next((p for p in prefixes if arg.startswith(p)), None)
        if prefix is not None:
            own.append("--" + arg[len(prefix):])
            own += [a for a in extra_args[i + 1 : i + 2] if not a.startswith("--")]
    if own:
        import tyro

        with PARSE_LOCK:  # tyro reads the options' docstrings from source
            config = tyro.cli(type(config), args=own, default=config)
    return _plain_options(dataclasses.asdict(config))


def _plain_options(options: Dict) -> Dict:
    """A config's `asdict` as JSON: paths as text, no `_target` (a preset's parts are nested configs, each with one)."""
    return {k: _plain_options(v) if isinstance(v, dict) else (str(v) if isinstance(v, Path) else v)
            for k, v in options.items() if k != "_target"}


def preference_model_hash(selector: str, options: Optional[Dict]) -> Optional[str]:
    """Hash of the preference model a selector loads (None for selectors without one)."""
    if options is None or "model" not in options:
        return None
    from hpgs_ns.selectors.preference_features import DEFAULT_MODEL

    path = Path(options["model"]) if options["model"] else DEFAULT_MODEL
    return file_hash(path) if path.is_file() else "missing"
