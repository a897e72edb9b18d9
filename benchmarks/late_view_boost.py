"""The late-view-boost pilot of issue #46 (docs/lab/late-view-boost-plan.md), read from its runs.

Reads `ROOT/<start>/<arm>/<scene>/fisherrf/<selector>/[final-set/]seed<k>.json` (start: `auto` or `active`; arm:
`off` or `b3`, i.e. `--pipeline.datamanager.late-view-boost 3`). Prints, per start: the gain b3 - off of the runs,
paired by (scene, selector, seed), with its 95% hierarchical-bootstrap interval (over scenes, `hpgs_lab.stats`) and
sign-flip p (over the pairs' scene means); each arm's schedule cost (final-set - run, same seed) per selector;
the same for `random`'s final-sets of both arms (no view is added there, so b3 - off is repeat noise); run time;
and the plan's decision. Writes it all as JSON.

    python benchmarks/late_view_boost.py [--root benchmarks/results/tune-boost] [--out ROOT/summary.json]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path
from statistics import mean
from typing import Dict, Tuple

from hpgs_lab import stats
from hpgs_ns.atomic_write import write_json_atomic

Key = Tuple[str, str, int]  # scene, selector, seed


def read_arm(folder: Path) -> Tuple[Dict[Key, dict], Dict[Key, dict]]:
    """{(scene, selector, seed): result} for the runs and for the final-sets under one arm's folder."""
    runs, finals = {}, {}
    for path in sorted(folder.glob("*/fisherrf/*/**/seed*.json")):
        data = json.loads(path.read_text())
        final = path.parent.name == "final-set"
        selector = path.parent.parent.name if final else path.parent.name
        key = (data["scene"], selector, int(data["seed"]))
        (finals if final else runs)[key] = data
    return runs, finals


def psnr(result: dict) -> float:
    return float(result["test"]["psnr"])


def summary(pairs: Dict[Key, float]) -> dict:
    """Mean of the pairs, hierarchical interval over scenes, sign-flip p over scene means."""
    by_scene: Dict[str, Dict[int, float]] = defaultdict(dict)
    for (scene, _selector, _seed), value in pairs.items():
        # a (selector, seed) pair is one replicate of the scene
        by_scene[scene][len(by_scene[scene])] = value
    est, lo, hi = stats.hierarchical_bootstrap(by_scene)
    p = stats.sign_flip_test(list(stats.scene_means(by_scene).values()))
    return {"mean": round(est, 3), "lo": round(lo, 3), "hi": round(hi, 3), "p": round(p, 4), "pairs": len(pairs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path("benchmarks/results/tune-boost"))
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    report: dict = {}
    for start_dir in sorted(p for p in args.root.iterdir() if p.is_dir()):
        start = start_dir.name
        (off_runs, off_finals), (b3_runs, b3_finals) = read_arm(start_dir / "off"), read_arm(start_dir / "b3")
        keys = sorted(set(off_runs) & set(b3_runs))
        gain = {k: psnr(b3_runs[k]) - psnr(off_runs[k]) for k in keys}
        selectors = sorted({k[1] for k in keys})
        out = {"gain_b3_minus_off": summary(gain),
               "gain_by_selector": {s: summary({k: v for k, v in gain.items() if k[1] == s}) for s in selectors}}
        cost = {}
        for arm, runs, finals in (("off", off_runs, off_finals), ("b3", b3_runs, b3_finals)):
            for s in selectors:
                pairs = {k: psnr(finals[k]) - psnr(runs[k]) for k in keys if k[1] == s and k in finals}
                cost[f"{arm}/{s}"] = summary(pairs)
        out["schedule_cost"] = cost
        noise = {k: psnr(b3_finals[k]) - psnr(off_finals[k]) for k in keys
                 if k[1] == "random" and k in b3_finals and k in off_finals}
        out["random_final_set_b3_minus_off"] = summary(noise)
        out["run_wall_s"] = {arm: round(mean(float(r["timing"]["wall_seconds"]) for r in runs.values()), 1)
                             for arm, runs in (("off", off_runs), ("b3", b3_runs))}
        out["per_scene_gain"] = {scene: round(mean(v for k, v in gain.items() if k[0] == scene), 3)
                                 for scene in sorted({k[0] for k in keys})}
        g = out["gain_b3_minus_off"]
        lower_cost = all(cost[f"b3/{s}"]["mean"] < cost[f"off/{s}"]["mean"] for s in selectors)
        out["decision"] = ("full-scale pilot" if g["mean"] >= 0.2 and g["p"] < 0.1 and lower_cost
                           else "stays off (rule not met)")
        report[start] = out
        print(f"== start {start}: {len(keys)} pairs")
        print(f"  gain b3 - off: {g['mean']:+.2f} dB [{g['lo']:+.2f}, {g['hi']:+.2f}], sign-flip p {g['p']:.3f}")
        for s, v in out["gain_by_selector"].items():
            print(f"    {s}: {v['mean']:+.2f} [{v['lo']:+.2f}, {v['hi']:+.2f}] p {v['p']:.3f}")
        for name, v in cost.items():
            print(f"  schedule cost {name}: {v['mean']:+.2f} [{v['lo']:+.2f}, {v['hi']:+.2f}] ({v['pairs']} pairs)")
        n = out["random_final_set_b3_minus_off"]
        print(f"  random final-sets b3 - off (repeat noise): {n['mean']:+.2f} [{n['lo']:+.2f}, {n['hi']:+.2f}]")
        print(f"  run wall s: {out['run_wall_s']}; per scene gain: {out['per_scene_gain']}")
        print(f"  decision: {out['decision']}")
    if args.out or report:
        write_json_atomic(args.out or args.root / "summary.json", report)


if __name__ == "__main__":
    main()
