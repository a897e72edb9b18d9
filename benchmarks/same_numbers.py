"""Seeded CPU runs of every built-in selector on a tiny synthetic scene: the views each picks and its test metrics.

A refactor that should not move any number is checked by running this before and after and comparing:

    python benchmarks/same_numbers.py --out /tmp/before.json --old-spelling   # on a commit before 0.3
    python benchmarks/same_numbers.py --out /tmp/after.json --compare /tmp/before.json

Since 0.4 the schedules follow --max-num-iterations (these runs: 60 steps); 0.3's numbers need
`--extra-args '--schedules-follow-steps False'`.

`--compare` exits 1 when a selector picked other views or a metric moved by more than `--tolerance`.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

SELECTORS = ("random", "farthest", "fisher", "hpgs", "condorcet", "blend")


def run_one(scene: Path, out: Path, selector: str, seed: int, steps: int, old_spelling: bool, extra=()) -> dict:
    from hpgs_ns.ns_train import ns_train_command

    eval_json = out / f"{selector}-eval.json"
    selection = {"select-every": steps // 3, "max-rounds": 2, "selector": selector}
    # Up to 0.2 the selection options were the datamanager's (`--old-spelling` runs an old commit).
    datamanager = {"num-initial-views": 6, "seed": seed, **(selection if old_spelling else {})}
    cmd = ns_train_command(
        scene, out, "same", selector, steps, datamanager=datamanager, selection=None if old_spelling else selection,
        model={"rasterizer": "cpu", "warmup-length": 20, "refine-every": 20, "num-downscales": 0,
               "sh-degree-interval": 20},
        trainer={"final-eval-json": eval_json}, extra=list(extra),
    )
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{selector}: ns-train failed:\n{proc.stderr[-3000:]}")
    from hpgs_ns.selection.log import SelectionLog

    log = SelectionLog.read(next((out / "same" / "hpgs" / selector).rglob("selected_views.json")))
    metrics = json.loads(eval_json.read_text())["results"]
    return {"views": log.active, "chosen": [r.chosen for r in log.rounds],
            "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics["lpips"]}


def compare(now: dict, before: dict, tolerance: float) -> list:
    problems = []
    for selector, old in before.items():
        new = now.get(selector)
        if new is None:
            problems.append(f"{selector}: missing")
            continue
        if new["chosen"] != old["chosen"]:
            problems.append(f"{selector}: chose {new['chosen']} (before: {old['chosen']})")
        for key in ("psnr", "ssim", "lpips"):
            if abs(new[key] - old[key]) > tolerance:
                problems.append(f"{selector}: {key} {new[key]:.6f} (before: {old[key]:.6f})")
    return problems


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="JSON file for the results")
    parser.add_argument("--compare", type=Path, help="results of an earlier commit to compare with")
    parser.add_argument("--selectors", nargs="+", default=list(SELECTORS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--tolerance", type=float, default=1e-4)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--old-spelling", action="store_true",
                        help="set the selection options as --pipeline.datamanager.* (hpgs-ns 0.2 and older)")
    parser.add_argument("--extra-args", default="",
                        help="more ns-train arguments, quoted (e.g. '--schedules-follow-steps False': 0.3's schedules)")
    args = parser.parse_args()

    from hpgs_ns.scenes.synthetic import make_scene

    work = Path(tempfile.mkdtemp(prefix="same-numbers-"))
    scene = make_scene(work / "ring", layout="ring", num_cameras=40, width=64, height=48, num_points=1500, seed=0)
    with ThreadPoolExecutor(args.jobs) as pool:
        futures = {s: pool.submit(run_one, scene, work / "runs", s, args.seed, args.steps, args.old_spelling,
                                  shlex.split(args.extra_args)) for s in args.selectors}
        results = {s: f.result() for s, f in futures.items()}
    args.out.write_text(json.dumps(results, indent=1))
    for selector, r in results.items():
        print(f"{selector:<10} PSNR {r['psnr']:.4f}  SSIM {r['ssim']:.4f}  LPIPS {r['lpips']:.4f}  chose {r['chosen']}")
    if args.compare is not None:
        problems = compare(results, json.loads(args.compare.read_text()), args.tolerance)
        print("\n".join(problems) if problems else f"same views and metrics within {args.tolerance:g} as {args.compare}")
        sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
