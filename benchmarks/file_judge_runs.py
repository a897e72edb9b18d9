"""File an `hpgs bench` results folder into the judge's layout, which `benchmarks/judge_table.py` reads.

`hpgs bench` writes `<out>/<scene>/fisherrf/<selector>/seed<k>.json` and the final-sets beside them
(`.../<selector>/final-set/seed<k>.json`); the judge keeps one folder per start mode,
`<root>/<scene>/<start>/<farthest|final-set>/seed<k>.json`, and `random` runs in `<start>-random/` beside their own
final-sets (judge_table pools each start's folders; farthest's and random's final-sets must not meet). Worst-view
JPEGs named in a run's JSON are copied beside it.

    hpgs bench --suite real6 --suite-scenes stitch --protocols fisherrf --selectors farthest random --seeds 0 1 \
        --no-references --final-set all --out runs/judge-active \
        --extra-args="--pipeline.datamanager.seed-points active"
    python benchmarks/file_judge_runs.py runs/judge-active active [--root benchmarks/results/judge-full]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import List

from hpgs_ns.atomic_write import write_json_atomic

ROOT = Path("benchmarks/results/judge-full")
SELECTORS = {"farthest": "", "random": "-random"}  # selector -> suffix of its start folder


def file_runs(bench_out: Path, start: str, root: Path = ROOT, protocol: str = "fisherrf") -> List[Path]:
    """Copy the farthest and random runs of `bench_out` (and their final-sets) into `root` under start `start`;
    returns the files written. An existing file is replaced (a re-run of the same run)."""
    written = []
    for path in sorted(Path(bench_out).glob(f"*/{protocol}/*/seed*.json")) + sorted(
            Path(bench_out).glob(f"*/{protocol}/*/final-set/seed*.json")):
        final_set = path.parent.name == "final-set"
        selector_dir = path.parent.parent if final_set else path.parent
        if selector_dir.name not in SELECTORS:
            continue
        scene = selector_dir.parent.parent.name
        data = json.loads(path.read_text())
        dest = root / scene / f"{start}{SELECTORS[selector_dir.name]}" / ("final-set" if final_set else selector_dir.name)
        out = dest / f"seed{data['seed']}.json"
        dest.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out, data)
        written.append(out)
        for worst in data.get("worst_views", []):
            jpg = path.parent / worst["image"]
            if jpg.is_file():
                shutil.copyfile(jpg, dest / worst["image"])
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bench_out", type=Path, help="an `hpgs bench --out` folder")
    parser.add_argument("start", help="the start mode its runs used (colmap, active, ...): the judge's folder name")
    parser.add_argument("--root", type=Path, default=ROOT)
    args = parser.parse_args()
    written = file_runs(args.bench_out, args.start, args.root)
    if not written:
        raise SystemExit(f"file_judge_runs: no farthest or random runs under {args.bench_out}/*/fisherrf/: "
                         "pass the folder given to `hpgs bench --out`")
    for out in written:
        print(out, round(json.loads(out.read_text())["test"]["psnr"], 2))


if __name__ == "__main__":
    main()
