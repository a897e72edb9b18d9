"""Test PSNR against training step in a trainer pilot (issue #46), mean over its runs: each arm's runs and `off`'s
final-sets, with splatfacto's opacity resets and the arm's restarts marked. Shows how the fit moves between
resets and what a restart does to it.

    python benchmarks/plot_pilot_curves.py [--root benchmarks/results/tune-boost] [--start auto] [--arm off r8-16] \
        [--restart-steps 1100 5700] [--reset-every 3000] [--out docs/lab/pilot-curves.png]

Reads `ROOT/<start>/<arm>/<scene>/fisherrf/<selector>/[final-set/]seed<k>.json` (`psnr_at_round_steps`: the test
PSNR just before each round's add, the run's end last). Writes the curves as JSON beside the PNG.

    python benchmarks/plot_pilot_curves.py --peaks benchmarks/results/tune-restart/full/off benchmarks/results/judge-full

prints instead, per scene, where the final-sets under those folders (any depth) score best and what they lose by the
end: a scene whose fit is best early rewards a mechanism for training less.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
from typing import Dict, List

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from hpgs_lab.results import RunResult, load_final_sets, load_results  # noqa: E402
from hpgs_ns.atomic_write import atomic_path, write_json_atomic  # noqa: E402


def mean_curve(results: List[RunResult]) -> Dict[int, float]:
    """{step: mean test PSNR} over results that share their round steps (the run's final step holds its end PSNR)."""
    at: Dict[int, List[float]] = defaultdict(list)
    for r in results:
        for step, psnr in r.psnr_at_round_steps.items():
            at[step].append(psnr)
        at[r.steps].append(r.test.psnr)
    return {step: float(np.mean(v)) for step, v in sorted(at.items())}


def peaks(final_sets: List[RunResult]) -> Dict[str, Dict[str, float]]:
    """scene -> {best_step, best_minus_end, end} of its final-sets' mean curve (`mean_curve`), the end included as
    a candidate for the best; final-sets without round-step PSNRs are left out."""
    by_scene: Dict[str, List[RunResult]] = defaultdict(list)
    for r in final_sets:
        if r.psnr_at_round_steps:
            by_scene[r.scene].append(r)
    out = {}
    for scene, results in sorted(by_scene.items()):
        curve = mean_curve(results)
        best = max(curve, key=lambda step: curve[step])
        end = curve[max(curve)]
        out[scene] = {"best_step": best, "best_minus_end": round(curve[best] - end, 3), "end": round(end, 3),
                      "final_sets": len(results)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path("benchmarks/results/tune-boost"))
    ap.add_argument("--start", default="auto")
    ap.add_argument("--arm", nargs="+", default=["off", "r8-16"])
    ap.add_argument("--restart-steps", type=int, nargs="*", default=[], help="steps to mark as the arms' restarts")
    ap.add_argument("--reset-every", type=int, default=3000, help="splatfacto's opacity-reset interval (steps)")
    ap.add_argument("--out", type=Path, default=Path("docs/lab/pilot-curves.png"))
    ap.add_argument("--peaks", type=Path, nargs="+", metavar="FOLDER",
                    help="print where the final-sets under these folders score best per scene, and stop")
    args = ap.parse_args()
    if args.peaks:
        for folder in args.peaks:
            found = [RunResult.from_json(p) for p in sorted(folder.glob("**/final-set/seed*.json"))]
            for scene, row in peaks(found).items():
                print(f"{folder.as_posix()} {scene}: best at step {row['best_step']}, "
                      f"{row['best_minus_end']:+.2f} dB over the end ({row['end']:.2f}; {row['final_sets']} final-sets)")
        return
    lines: Dict[str, Dict[int, float]] = {}
    for arm in args.arm:
        folder = args.root / args.start / arm
        runs = [r for r in load_results(folder) if not r.repeat and not r.is_reference]
        lines[f"{arm}: runs"] = mean_curve(runs)
        if arm == args.arm[0]:
            lines[f"{arm}: final-sets (the runs' views from step 0)"] = mean_curve(load_final_sets(folder))
        print(f"{arm}: {len(runs)} runs; end {list(lines[f'{arm}: runs'].values())[-1]:.2f} dB")
    fig, ax = plt.subplots(figsize=(8, 4))
    last = max(max(c) for c in lines.values())
    for k, step in enumerate(range(args.reset_every, last, args.reset_every)):
        ax.axvline(step, color="gray", linestyle="--", linewidth=0.8, label="opacity reset" if k == 0 else None)
    for k, step in enumerate(args.restart_steps):
        ax.axvline(step, color="green", linestyle=":", label="restart" if k == 0 else None)
    for name, curve in lines.items():
        ax.plot(list(curve), list(curve.values()), marker="o", markersize=3, label=name)
    ax.set_xlabel("training step")
    ax.set_ylabel("test PSNR (dB), mean over runs")
    ax.set_title(f"Test PSNR during training ({args.root.name}, {args.start} start)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(args.out, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    write_json_atomic(args.out.with_suffix(".json"), {name: {str(s): round(v, 3) for s, v in c.items()}
                                                      for name, c in lines.items()})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
