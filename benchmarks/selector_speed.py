"""Seconds per selection round for each selector on a real scene (the GPU figures in docs/lab/bonsai-and-selection-cost.md).

Trains `ns-train hpgs` for `--steps` steps with one round at the last step, for each selector, and writes
OUT/selector_speed.json with the round's seconds, the number of candidates and the Gaussian count. `fisher` runs
once per `--fisher-criteria` entry (`trace`, FisherRF's; `dopt` and `dopt-block`, POp-GS's), each its own row.

    python benchmarks/selector_speed.py --scene PATH --out DIR [--steps 2000] [--selectors hpgs fisher ...]
        [--fisher-criteria trace dopt dopt-block] [--extra "--pipeline.model.rasterizer cpu"]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import List, Optional, Tuple

import torch

from hpgs_ns.ns_train import SELECTION_PREFIX
from hpgs_ns.selection.log import SelectionLog


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--downscale-factor", type=int, default=2)
    ap.add_argument("--selectors", nargs="+", default=["random", "farthest", "hpgs", "fisher", "condorcet"])
    ap.add_argument("--rounds", type=int, default=1, help="rounds, evenly spaced; the first pays one-off CUDA set-up")
    ap.add_argument("--fisher-criteria", nargs="+", default=["trace", "dopt", "dopt-block"],
                    help="fisher's criteria, a row each (--pipeline.selection.fisher.criterion)")
    ap.add_argument("--extra", default="", help="extra ns-train arguments")
    args = ap.parse_args()
    results = []
    for sel, criterion in runs(args.selectors, args.fisher_criteria):
        label = sel if criterion in (None, "trace") else f"{sel}-{criterion}"  # trace keeps fisher's old run folder
        options = [] if criterion is None else [f"--{SELECTION_PREFIX}fisher.criterion", criterion]
        cmd = [
            sys.executable, "-m", "nerfstudio.scripts.train", "hpgs", "--data", str(args.scene),
            "--output-dir", str(args.out / "runs"), "--experiment-name", "speed", "--timestamp", label,
            "--vis", "tensorboard", "--max-num-iterations", str(args.steps + 1), "--steps-per-save", str(10 * args.steps),
            "--steps-per-eval-all-images", str(10 * args.steps), "--steps-per-eval-image", str(10 * args.steps),
            f"--{SELECTION_PREFIX}select-every", str(args.steps // args.rounds),
            f"--{SELECTION_PREFIX}max-rounds", str(args.rounds),
            f"--{SELECTION_PREFIX}selector", sel, *options,
            *args.extra.split(), "mipnerf360", "--downscale-factor", str(args.downscale_factor),
        ]
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"selector_speed: {label} run failed:\n" + "\n".join(proc.stderr.splitlines()[-30:]))
        log = SelectionLog.read(args.out / "runs" / "speed" / "hpgs" / label)
        ckpt = sorted((args.out / "runs" / "speed" / "hpgs" / label / "nerfstudio_models").glob("*.ckpt"))[-1]
        n = torch.load(ckpt, map_location="cpu", weights_only=True)["pipeline"]["_model.gauss_params.means"].shape[0]
        r = log.rounds[-1]
        row = {"selector": sel, **({} if criterion is None else {"criterion": criterion}), "round_seconds": r.seconds,
               "all_round_seconds": [x.seconds for x in log.rounds],
               "work": r.work, "candidates": len(r.scores),
               "active_before": r.num_active - len(r.chosen), "gaussians": int(n), "chosen": r.chosen,
               "wall_seconds": time.perf_counter() - start,
               "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"}
        print(json.dumps(row), flush=True)
        results.append(row)
    (args.out / "selector_speed.json").write_text(json.dumps(results, indent=2))


def runs(selectors: List[str], fisher_criteria: List[str]) -> List[Tuple[str, Optional[str]]]:
    """(selector, fisher criterion or None) for each run, fisher's criteria in the place of `fisher`."""
    return [(sel, c) for sel in selectors for c in (fisher_criteria if sel == "fisher" else [None])]


if __name__ == "__main__":
    main()
