"""How long the CLIs take to print their help: `hpgs --help`, `hpgs CMD --help` for every subcommand, and
`ns-train hpgs --help` against stock `ns-train splatfacto --help`, with this plugin installed and with it hidden
from nerfstudio's plugin discovery (nerfstudio imports every installed method plugin for any `ns-train` call, so
the difference of the two splatfacto rows is what the plugin adds to every `ns-train`).

Each command runs once untimed (a warm file cache and .pyc files), then `--runs` times timed; the table gives the
median wall seconds. A command that fails, or prints anything on stderr (a warning), is flagged in the table and in
the JSON. Writes the JSON to --out with the machine's core count and load average.

    python benchmarks/help_time.py [--out benchmarks/results/help_time.json] [--runs 3] [--only hpgs]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List

# Where the console scripts of this interpreter's environment live (the venv's bin/).
BIN = Path(sys.executable).parent

# `ns-train ARGS` with the `hpgs` entry point left out of nerfstudio's plugin discovery (what ns-train costs without
# this plugin installed); argv: python -c NS_TRAIN_WITHOUT_PLUGIN ARGS...
NS_TRAIN_WITHOUT_PLUGIN = """
import importlib.metadata as md, sys
entry_points = md.entry_points
def without_hpgs(**kwargs):
    found = entry_points(**kwargs)
    if kwargs.get("group") == "nerfstudio.method_configs":
        return md.EntryPoints(e for e in found if not e.value.startswith("hpgs_ns"))
    return found
md.entry_points = without_hpgs
sys.argv = ["ns-train", *sys.argv[1:]]
from nerfstudio.scripts.train import entrypoint
entrypoint()
"""


def commands() -> Dict[str, List[str]]:
    """label -> argv, in table order."""
    from hpgs_ns.cli import all_commands

    hpgs, ns_train = str(BIN / "hpgs"), str(BIN / "ns-train")
    out = {"hpgs --help": [hpgs, "--help"]}
    out.update({f"hpgs {name} --help": [hpgs, name, "--help"] for name in all_commands()})
    out["ns-train hpgs --help"] = [ns_train, "hpgs", "--help"]
    out["ns-train splatfacto --help"] = [ns_train, "splatfacto", "--help"]
    out["ns-train splatfacto --help, no plugin"] = [sys.executable, "-c", NS_TRAIN_WITHOUT_PLUGIN, "splatfacto", "--help"]
    return out


def git_commit() -> str:
    """HEAD of the checkout this script is in, with `+dirty` if the tree has changes (the code timed, unless
    PYTHONPATH points elsewhere)."""
    root = Path(__file__).resolve().parent.parent
    git = lambda *a: subprocess.run(["git", *a], cwd=root, capture_output=True, text=True).stdout.strip()  # noqa: E731
    head = git("rev-parse", "--short", "HEAD")
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def run_once(argv: List[str]) -> dict:
    start = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True)
    return {"seconds": time.perf_counter() - start, "rc": proc.returncode, "stderr": proc.stderr.strip()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/help_time.json"))
    ap.add_argument("--runs", type=int, default=3, help="timed runs per command (after one untimed)")
    ap.add_argument("--only", default="", help="only the commands whose label contains this text")
    ap.add_argument("--note", default="", help="stored in the JSON (e.g. which code was timed)")
    args = ap.parse_args()

    load_at_start = os.getloadavg()
    rows = []
    print(f"{'command':<40} {'median s':>9} {'min s':>7} {'max s':>7}  notes")
    for label, argv in commands().items():
        if args.only not in label:
            continue
        run_once(argv)  # untimed: warm caches
        runs = [run_once(argv) for _ in range(args.runs)]
        seconds = [r["seconds"] for r in runs]
        failed = [r for r in runs if r["rc"] != 0]
        stderr = next((r["stderr"] for r in runs if r["stderr"]), "")
        notes = (f"FAILED rc={failed[0]['rc']} " if failed else "") + (f"stderr: {stderr.splitlines()[0]}" if stderr else "")
        shown = ["python", "-c", "NS_TRAIN_WITHOUT_PLUGIN"] + argv[3:] if argv[1] == "-c" else [Path(argv[0]).name] + argv[1:]
        row = {"command": label, "argv": shown, "median_seconds": statistics.median(seconds),
               "seconds": seconds, "ok": not failed, "stderr": stderr}
        rows.append(row)
        print(f"{label:<40} {row['median_seconds']:>9.2f} {min(seconds):>7.2f} {max(seconds):>7.2f}  {notes[:100]}", flush=True)

    result = {
        "what": "wall seconds of each CLI's --help; median of the timed runs after one untimed run",
        "runs": args.runs,
        "note": args.note,
        "git_commit": git_commit(),
        "pythonpath": os.environ.get("PYTHONPATH", ""),
        "cpu_count": os.cpu_count(),
        "load_average_at_start": load_at_start,
        "load_average_at_end": os.getloadavg(),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "env": {k: os.environ[k] for k in ("OMP_NUM_THREADS",) if k in os.environ},
        "commands": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
