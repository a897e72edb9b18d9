"""The restart pilot of docs/active-training.md: per-run test PSNR and the paired gain of `restart-at-views 8 16`.

Reads `benchmarks/results/schedule-pilot/<scene>-<start>/<variant>/seed<k>.json` (variants `follow`: no restart,
`restart-8-16`, `finalset-follow`: the same final views from step 0), prints the table and the paired gains
(`hpgs_lab.stats`: mean of per-scene means, hierarchical bootstrap over scenes), and writes them as JSON.

    python benchmarks/restart_pilot.py [--out benchmarks/results/schedule-pilot/restart_pilot.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

from hpgs_lab import stats
from hpgs_ns.atomic_write import write_json_atomic

ROOT = Path("benchmarks/results/schedule-pilot")
VARIANTS = ("follow", "restart-8-16", "finalset-follow")
JUDGED = ("fox",)  # real6 scenes: not used to choose the setting


def load(root: Path):
    rows = []
    for path in sorted(root.glob("*/*/seed*.json")):
        variant, group = path.parent.name, path.parent.parent.name
        if variant not in VARIANTS:
            continue
        data = json.loads(path.read_text())
        test = SimpleNamespace(**{k: data["test"][k] for k in ("psnr", "ssim", "lpips")})
        rows.append(SimpleNamespace(scene=group, protocol="fisherrf", selector=variant, seed=int(data["seed"]), test=test))
    return rows


def gain(rows, groups, a: str, b: str, metric: str):
    sub = [r for r in rows if r.scene in groups]
    gains = stats.paired_gains(sub, a, b, "fisherrf", metric)
    if not gains:
        return None
    mean, lo, hi = stats.hierarchical_bootstrap(gains, n_boot=10000, seed=0)
    return {"a": a, "b": b, "metric": metric, "scenes": len(gains), "pairs": sum(len(v) for v in gains.values()),
            "mean": mean, "lo": lo, "hi": hi, "per_scene": stats.scene_means(gains)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT)
    parser.add_argument("--out", type=Path, default=ROOT / "restart_pilot.json")
    args = parser.parse_args()
    rows = load(args.root)
    groups = sorted({r.scene for r in rows})
    print("| scene, start | " + " | ".join(VARIANTS) + " |")
    print("|---" * (len(VARIANTS) + 1) + "|")
    for g in groups:
        cells = []
        for v in VARIANTS:
            seeds = {r.seed: r.test.psnr for r in rows if r.scene == g and r.selector == v}
            cells.append(" / ".join(f"{seeds[s]:.2f}" for s in sorted(seeds)) or "-")
        print(f"| {g} | " + " | ".join(cells) + " |")
    random_tune = [g for g in groups if g.endswith("-random") and not g.startswith(JUDGED)]
    random_judged = [g for g in groups if g.endswith("-random") and g.startswith(JUDGED)]
    seeded = [g for g in groups if not g.endswith("-random")]
    summary = {}
    for label, part in (("random, tuning", random_tune), ("random, judged", random_judged), ("seeded, tuning", seeded)):
        for metric in ("psnr", "ssim"):
            g = gain(rows, part, "restart-8-16", "follow", metric)
            if g:
                summary[f"restart - follow, {label}, {metric}"] = g
    for variant in ("follow", "restart-8-16"):
        g = gain(rows, random_tune + random_judged, "finalset-follow", variant, "psnr")
        if g:
            summary[f"schedule cost of {variant}, random starts, psnr"] = g
    print()
    for name, g in summary.items():
        print(f"{name}: {g['mean']:+.2f} [{g['lo']:+.2f}, {g['hi']:+.2f}] ({g['scenes']} scenes, {g['pairs']} pairs)")
    write_json_atomic(args.out, summary)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
