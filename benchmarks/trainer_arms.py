"""A trainer setting's arms against the trainer's defaults (`off`), read from their runs: a trainer pilot's table.

Reads `ROOT/<start>/<arm>/<scene>/fisherrf/<selector>/[final-set/]seed<k>.json` (start: `auto` or `active`; arm:
`off`, the trainer's defaults, or one setting, e.g. `w0.05` for `--pipeline.model.depth-loss.weight 0.05`). Prints,
per start and arm: the gain arm - off of the runs, paired by (scene, selector, seed), with its 95%
hierarchical-bootstrap interval (over scenes, `hpgs_lab.stats`) and sign-flip p (over the pairs' scene means); each
arm's schedule cost (final-set - run, same seed) per selector; arm - off on `random`'s final-sets (views that do not
depend on training: repeat noise, or what the mechanism does to a run without adds); run time; and the plans'
earlier plans' decision rule (gain >= +0.2 dB, p < 0.1, lower schedule cost for every selector). Writes it all as
JSON.

    python benchmarks/trainer_arms.py [--root benchmarks/results/tune-boost] [--baseline off] [--out ROOT/summary.json]
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
from statistics import mean
from typing import Dict, Tuple

from hpgs_lab import stats
from hpgs_lab.report.schedule import schedule_pairs
from hpgs_lab.results import RunResult, load_final_sets, load_results
from hpgs_ns.atomic_write import write_json_atomic

Key = Tuple[str, str, int]  # scene, selector, seed


def read_arm(folder: Path, protocol: str = "fisherrf") -> Tuple[Dict[Key, RunResult], Dict[Key, RunResult]]:
    """{(scene, selector, seed): result} for one protocol's runs (first repeats) under one arm's folder, and for the
    current final-sets of those runs (`schedule_pairs`: one whose run has other views now is left out)."""
    # a judge folder holds the HP-GS protocol's runs too: keys are per protocol
    runs = {(r.scene, r.selector, r.seed): r for r in load_results(folder)
            if not r.repeat and not r.is_reference and r.protocol == protocol}
    pairs, _ = schedule_pairs(list(runs.values()), load_final_sets(folder))
    return runs, {(p.run.scene, p.run.selector, p.run.seed): p.final for p in pairs}


def psnr(result: RunResult) -> float:
    return float(result.test.psnr)


def summary(pairs: Dict[Key, float]) -> dict:
    """Mean of the pairs, hierarchical interval over scenes, sign-flip p over scene means."""
    by_scene: Dict[str, Dict[int, float]] = defaultdict(dict)
    for (scene, _selector, _seed), value in pairs.items():
        # a (selector, seed) pair is one replicate of the scene
        by_scene[scene][len(by_scene[scene])] = value
    out = stats.across_scenes(by_scene)
    return {"mean": round(out["mean"], 3), "lo": round(out["lo"], 3), "hi": round(out["hi"], 3), "p": round(out["p"], 4),
            "pairs": len(pairs)}


def compare(start_dir: Path, baseline: str, arm: str) -> dict:
    """One arm against the baseline arm of one start: gains, schedule costs, noise, run time, decision."""
    (off_runs, off_finals), (arm_runs, arm_finals) = read_arm(start_dir / baseline), read_arm(start_dir / arm)
    keys = sorted(set(off_runs) & set(arm_runs))
    gain = {k: psnr(arm_runs[k]) - psnr(off_runs[k]) for k in keys}
    selectors = sorted({k[1] for k in keys})
    out = {"gain": summary(gain),
           "gain_by_selector": {s: summary({k: v for k, v in gain.items() if k[1] == s}) for s in selectors}}
    cost = {}
    for name, runs, finals in ((baseline, off_runs, off_finals), (arm, arm_runs, arm_finals)):
        for s in selectors:
            pairs = {k: psnr(finals[k]) - psnr(runs[k]) for k in keys if k[1] == s and k in finals}
            cost[f"{name}/{s}"] = summary(pairs)
    out["schedule_cost"] = cost
    noise = {k: psnr(arm_finals[k]) - psnr(off_finals[k]) for k in keys
             if k[1] == "random" and k in arm_finals and k in off_finals}
    out["random_final_set_difference"] = summary(noise)
    out["run_wall_s"] = {name: round(mean(float(runs[k].timing.wall_seconds) for k in keys), 1)
                         for name, runs in ((baseline, off_runs), (arm, arm_runs))}
    out["per_scene_gain"] = {scene: round(mean(v for k, v in gain.items() if k[0] == scene), 3)
                             for scene in sorted({k[0] for k in keys})}
    g = out["gain"]
    lower_cost = all(cost[f"{arm}/{s}"]["mean"] < cost[f"{baseline}/{s}"]["mean"] for s in selectors)
    out["decision"] = "qualifies" if g["mean"] >= 0.2 and g["p"] < 0.1 and lower_cost else "rule not met"
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path("benchmarks/results/tune-boost"))
    ap.add_argument("--baseline", default="off", help="the arm the others are paired with")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    report: dict = {}
    for start_dir in sorted(p for p in args.root.iterdir() if (p / args.baseline).is_dir()):
        arms = sorted(p.name for p in start_dir.iterdir() if p.is_dir() and p.name != args.baseline)
        for arm in arms:
            out = report.setdefault(start_dir.name, {})[arm] = compare(start_dir, args.baseline, arm)
            g, n = out["gain"], out["random_final_set_difference"]
            print(f"== start {start_dir.name}, {arm} - {args.baseline}: {g['pairs']} pairs")
            print(f"  gain: {g['mean']:+.2f} dB [{g['lo']:+.2f}, {g['hi']:+.2f}], sign-flip p {g['p']:.3f}")
            for s, v in out["gain_by_selector"].items():
                print(f"    {s}: {v['mean']:+.2f} [{v['lo']:+.2f}, {v['hi']:+.2f}] p {v['p']:.3f}")
            for name, v in out["schedule_cost"].items():
                print(f"  schedule cost {name}: {v['mean']:+.2f} [{v['lo']:+.2f}, {v['hi']:+.2f}] ({v['pairs']} pairs)")
            print(f"  random final-sets, {arm} - {args.baseline}: {n['mean']:+.2f} [{n['lo']:+.2f}, {n['hi']:+.2f}]")
            print(f"  run wall s: {out['run_wall_s']}; per scene gain: {out['per_scene_gain']}")
            print(f"  decision: {out['decision']}")
    write_json_atomic(args.out or args.root / "summary.json", report)


if __name__ == "__main__":
    main()
