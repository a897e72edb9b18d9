"""Files written so that no reader ever sees half of one: a temporary file beside the target, then a rename.

Sweeps, labelling sessions and training runs can be killed at any moment; a rename within one folder is atomic
on POSIX, so the target holds either its old or its new content. (The standard library has no such writer.)
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Dict, Iterator, Optional, Sequence


@contextlib.contextmanager
def atomic_path(path: Path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary path beside `path` to write to; renamed over `path` (with the usual permissions: mkstemp
    makes 0600) when the block ends, removed if it raises. `suffix`: e.g. ".png" where the writer reads the
    format from the name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: Path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json_atomic(path: Path, payload: Any, indent: int = 2) -> Path:
    return write_text_atomic(path, json.dumps(payload, indent=indent) + "\n")


def write_csv_atomic(path: Path, fieldnames: Sequence[str], rows: Sequence[Dict[str, object]]) -> Path:
    """A CSV with a header, written to a temporary file, fsynced, then renamed over `path` (and the rename made
    durable): a labelling session confirms an answer only after this returns. Keys not in `fieldnames` are
    ignored."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(fieldnames), extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
        f.flush()
        os.fsync(f.fileno())
    _fsync_dir(path.parent)
    return path


@contextlib.contextmanager
def removed_on_failure(folder: Path, expected: Dict[str, str], stop_at: Optional[Path] = None) -> Iterator[bool]:
    """Remove `folder` if the block raises, provided it held exactly the files `expected` ({name: text}) when the
    block began: what the caller's own process wrote there just before (a run folder holding ns-train's config.yml
    and nothing else). A folder holding anything else is left alone. Its parents below `stop_at` that are left
    empty go too. Yields whether `folder` is removed on failure."""
    folder = Path(folder)
    try:
        fresh = folder.is_dir() and sorted(p.name for p in folder.iterdir()) == sorted(expected) and all(
            (folder / name).read_text(encoding="utf-8") == text for name, text in expected.items())
    except (OSError, UnicodeDecodeError):
        fresh = False
    try:
        yield fresh
    except BaseException:
        if fresh:
            shutil.rmtree(folder, ignore_errors=True)
            parent, stop = folder.resolve().parent, Path(stop_at).resolve() if stop_at is not None else None
            while stop is not None and stop in parent.parents:
                try:
                    parent.rmdir()  # only if empty
                except OSError:
                    break
                parent = parent.parent
        raise


def _fsync_dir(directory: Path) -> None:
    """Make a rename durable (POSIX); a no-op where directories cannot be opened."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
