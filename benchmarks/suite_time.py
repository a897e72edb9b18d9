"""Wall time of the test suite at two commits, back to back on this machine, each as its own `make test` ran it.

Each commit is checked out in a git worktree beside the repository (so `../shared` resolves as in CI) and its
tests run with this venv's Python (`PYTHONPATH` = the worktree): before 0.4 one process, since then
`-n 2 --dist loadfile` (pytest-xdist). Prints the figures and writes them as JSON.

    python benchmarks/suite_time.py --before 2bbac07 --after HEAD --out benchmarks/results/suite_time.json
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from hpgs_ns.atomic_write import write_json_atomic

ROOT = Path(__file__).resolve().parents[1]


def pytest_args(worktree: Path) -> list:
    """The commit's own test command (its Makefile says whether it runs several processes)."""
    makefile = (worktree / "Makefile").read_text()
    parallel = ["-n", "2", "--dist", "loadfile"] if "--dist loadfile" in makefile else []
    return [sys.executable, "-m", "pytest", "-q", "-ra", *parallel, "tests", "-p", "no:cacheprovider"]


def time_suite(commit: str) -> dict:
    sha = subprocess.run(["git", "rev-parse", "--short", commit], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.strip()
    worktree = ROOT.parent / f"wt-{sha}"
    if not worktree.exists():
        subprocess.run(["git", "worktree", "add", "-f", "-q", str(worktree), sha], cwd=ROOT, check=True)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(worktree))
    args = pytest_args(worktree)
    start = time.perf_counter()
    proc = subprocess.run(args, cwd=worktree, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    counts = {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|skipped|errors?)", summary)}
    return {"commit": sha, "command": " ".join(args[1:]), "wall_seconds": round(wall, 1), "summary": summary,
            **counts, "returncode": proc.returncode}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="2bbac07")
    parser.add_argument("--after", default="HEAD")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/suite_time.json"))
    args = parser.parse_args()
    before, after = time_suite(args.before), time_suite(args.after)
    result = {"machine": f"{os.cpu_count()} cores", "before": before, "after": after,
              "fall_seconds": round(before["wall_seconds"] - after["wall_seconds"], 1)}
    for name in ("before", "after"):
        r = result[name]
        print(f"{name:<6} {r['commit']}: {r['wall_seconds']:.0f} s  ({r['summary']})")
    print(f"fall: {result['fall_seconds']:.0f} s")
    write_json_atomic(args.out, result)


if __name__ == "__main__":
    main()
