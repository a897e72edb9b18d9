"""Where the schedule cost lands (issue #46): per test view, final-set PSNR - run PSNR, grouped by when the training
view nearest to it (by camera centre) joined the run, and by how much of what it sees the run had from step 0.

Reads runs laid out as `ROOT/<start>/<arm>/<scene>/fisherrf/<selector>/[final-set/]seed<k>.json` (as
`benchmarks/late_view_boost.py`) and each scene's COLMAP poses from `--data-root/<scene>/sparse/0`. A test view
nearest an initial view is grouped `initial`; else by the round that added its nearest view (1-8, 9-12, 13-16).
Prints each start's mean cost per group for one arm, and the other arm's run PSNR minus this one's per group
(same views, so only for selectors whose views do not depend on training, e.g. `random`). Then by geometry: the
share of the test view's COLMAP points (the model's tracks) that an initial view observes, in thirds of the test
views, with the correlation of that share and the cost within each (scene, selector). Writes JSON.

    python benchmarks/schedule_cost_views.py [--root benchmarks/results/tune-boost] [--arm off] [--other b3] \
        [--data-root ../shared/data] [--out ROOT/cost_by_view.json] [--plot docs/lab/schedule-cost-by-round.png]

`--arm off r8-16`: several arms, each reported (JSON `{arm: {start: ...}}`) and drawn as lines of their own.

`--plot`: the mean cost per round of the nearest view (standard errors), one line per start, with the step each
round arrived at and where splatfacto's SH degree 1 opens (`--sh-degree-interval`, splatfacto's 1000).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path
from typing import Dict, List

import numpy as np

from hpgs_lab.report.cost_by_round import GROUPS
from hpgs_lab.report.schedule import schedule_pairs
from hpgs_lab.results import load_final_sets, load_results
from hpgs_ns.atomic_write import write_json_atomic
from hpgs_ns.scenes.colmap_model import read_images, read_points3D


def images(data_root: Path, scene: str, cache: Dict[tuple, dict]) -> dict:
    """The scene's COLMAP images (read once per scene)."""
    key = ("images", scene)
    if key not in cache:
        cache[key] = read_images(data_root / scene / "sparse" / "0") or {}
    return cache[key]


def centres(data_root: Path, scene: str, cache: Dict[tuple, dict]) -> Dict[str, np.ndarray]:
    """{'images/<name>': camera centre} from the scene's COLMAP model (the names the runs record)."""
    key = ("centres", scene)
    if key not in cache:
        cache[key] = {f"images/{im.name}": -im.qvec2rotmat().T @ im.tvec
                      for im in images(data_root, scene, cache).values()} or transforms_centres(data_root / scene)
    return cache[key]


def transforms_centres(folder: Path) -> Dict[str, np.ndarray]:
    """{file_path: camera centre} from a nerfstudio capture's transforms.json (camera-to-world: the centre is the
    translation), for scenes without a COLMAP model (fox); empty when it has neither."""
    path = folder / "transforms.json"
    if not path.is_file():
        return {}
    frames = json.loads(path.read_text())["frames"]
    return {f["file_path"]: np.asarray(f["transform_matrix"], dtype=float)[:3, 3] for f in frames}


def observed(data_root: Path, scene: str, cache: Dict[tuple, dict]) -> Dict[str, set]:
    """{'images/<name>': ids of the COLMAP points that image observes} from the scene's model's tracks."""
    key = ("tracks", scene)
    if key not in cache:
        names = {i: f"images/{im.name}" for i, im in images(data_root, scene, cache).items()}
        seen: Dict[str, set] = defaultdict(set)
        for pid, point in (read_points3D(data_root / scene / "sparse" / "0") or {}).items():
            for iid in set(point.image_ids.tolist()):
                seen[names[iid]].add(pid)
        cache[key] = seen
    return cache[key]


def group_of(round_added: int) -> str:
    return next(name for name, lo, hi in GROUPS if lo <= round_added <= hi)


def view_rows(root: Path, start: str, arm: str, data_root: Path, cache: Dict[tuple, dict]) -> List[dict]:
    """One row per (run, test view): its run PSNR, its final-set PSNR, its nearest training view's round and the
    share of its COLMAP points an initial view observes (None without points)."""
    rows = []
    folder = root / start / arm
    for pair in schedule_pairs(load_results(folder), load_final_sets(folder))[0]:
        run = pair.run
        where = centres(data_root, run.scene, cache)
        order = list(run.initial_views) + list(run.chosen_views)
        added = {name: max(i - len(run.initial_views) + 1, 0) for i, name in enumerate(order)}
        final_psnr = {v.name: v.psnr for v in pair.final.test_views}
        seen = observed(data_root, run.scene, cache)
        at_start = set().union(*(seen[name] for name in run.initial_views))
        # how new an added view was when it came: distance to the nearest camera then active, over the final views'
        # median nearest-neighbour spacing
        spacing = float(np.median([min(float(np.linalg.norm(where[a] - where[b])) for b in order if b != a)
                                   for a in order])) or 1.0
        novelty = {name: min(float(np.linalg.norm(where[name] - where[b])) for b in order[:i]) / spacing
                   for i, name in enumerate(order) if i >= len(run.initial_views)}
        for view in run.test_views:
            points = seen[view.name]
            nearest = min(order, key=lambda name: float(np.linalg.norm(where[name] - where[view.name])))
            rows.append({"scene": run.scene, "selector": run.selector, "seed": run.seed,
                         "view": view.name, "run": view.psnr, "final_set": final_psnr[view.name],
                         "group": group_of(added[nearest]), "round": added[nearest],
                         "round_steps": [int(r.step) for r in run.psnr_per_round],
                         "initial_share": len(points & at_start) / len(points) if points else None,
                         "novelty": novelty.get(nearest)})
    return rows


def geometry(rows: List[dict], field: str = "initial_share") -> dict:
    """Cost by thirds of `field` (the share seen from step 0, or the nearest added view's novelty at its arrival),
    and its correlation with the cost within (scene, selector)."""
    rows = [r for r in rows if r[field] is not None]
    values = np.array([r[field] for r in rows])
    cost = np.array([r["final_set"] - r["run"] for r in rows])
    edges = np.quantile(values, [0, 1 / 3, 2 / 3, 1])
    thirds = []
    for k in range(3):
        inside = (values >= edges[k]) & ((values < edges[k + 1]) if k < 2 else (values <= edges[k + 1]))
        thirds.append({"share": [round(float(edges[k]), 3), round(float(edges[k + 1]), 3)],
                       "mean": round(float(cost[inside].mean()), 3), "views": int(inside.sum())})
    key = [(r["scene"], r["selector"]) for r in rows]
    d_values, d_cost = values.copy(), cost.copy()
    for k in set(key):
        m = np.array([x == k for x in key])
        d_values[m] -= values[m].mean()
        d_cost[m] -= cost[m].mean()
    return {"thirds": thirds, "within_corr": round(float(np.corrcoef(d_values, d_cost)[0, 1]), 3)}


def means(values: Dict[str, List[float]]) -> Dict[str, dict]:
    return {g: {"mean": round(float(np.mean(v)), 3), "views": len(v)} for g, v in values.items() if v}


def arm_report(root: Path, start: str, arm: str, other: str, data_root: Path, cache: Dict[tuple, dict]) -> dict:
    """One start's and arm's cost per group, per round and by geometry (and `other`'s run PSNR minus this arm's)."""
    rows = view_rows(root, start, arm, data_root, cache)
    cost: Dict[str, List[float]] = defaultdict(list)
    per_selector: Dict[str, Dict[str, List[float]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        cost[r["group"]].append(r["final_set"] - r["run"])
        per_selector[r["selector"]][r["group"]].append(r["final_set"] - r["run"])
    entry = {"cost_by_group": means({g: cost[g] for g, _, _ in GROUPS})}
    entry["cost_by_group_by_selector"] = {sel: means({g: groups[g] for g, _, _ in GROUPS})
                                          for sel, groups in per_selector.items()}
    if other and (root / start / other).is_dir():
        twins = {(r["scene"], r["selector"], r["seed"], r["view"]): r
                 for r in view_rows(root, start, other, data_root, cache)}
        diff: Dict[str, List[float]] = defaultdict(list)
        for r in rows:
            twin = twins.get((r["scene"], r["selector"], r["seed"], r["view"]))
            if r["selector"] == "random" and twin is not None:
                diff[r["group"]].append(twin["run"] - r["run"])
        entry[f"random_run_{other}_minus_{arm}_by_group"] = means({g: diff[g] for g, _, _ in GROUPS})
    entry["by_initial_share"] = geometry(rows)
    entry["by_novelty"] = geometry(rows, "novelty")
    by_round: Dict[int, List[float]] = defaultdict(list)
    for r in rows:
        by_round[r["round"]].append(r["final_set"] - r["run"])
    entry["cost_by_round"] = {str(k): {"mean": round(float(np.mean(v)), 3), "views": len(v),
                                       "se": round(float(np.std(v, ddof=1) / np.sqrt(len(v))), 3) if len(v) > 1 else None}
                              for k, v in sorted(by_round.items())}
    entry["round_steps"] = next((r["round_steps"] for r in rows if r["round_steps"]), [])
    print(f"== {start}, {arm} ({len(rows)} test views)")
    for g, _, _ in GROUPS:
        c = entry["cost_by_group"].get(g)
        d = entry.get(f"random_run_{other}_minus_{arm}_by_group", {}).get(g)
        print(f"  nearest view {g:>13}: cost {c['mean']:+.2f} dB ({c['views']} views)" if c else f"  {g}: none",
              f"| random run {other} - {arm} {d['mean']:+.2f} ({d['views']})" if d else "")
    geo = entry["by_initial_share"]
    for third in geo["thirds"]:
        print(f"  share seen from step 0 {third['share'][0]:.2f}-{third['share'][1]:.2f}: cost {third['mean']:+.2f} dB "
              f"({third['views']} views)")
    print(f"  within (scene, selector): corr(share, cost) {geo['within_corr']:+.3f}")
    new = entry["by_novelty"]
    for third in new["thirds"]:
        print(f"  nearest added view's novelty {third['share'][0]:.2f}-{third['share'][1]:.2f} spacings: cost "
              f"{third['mean']:+.2f} dB ({third['views']} views)")
    print(f"  within (scene, selector): corr(novelty, cost) {new['within_corr']:+.3f}")
    return entry


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path("benchmarks/results/tune-boost"))
    ap.add_argument("--arm", nargs="+", default=["off"], help="one or more arms (a line each in --plot)")
    ap.add_argument("--other", default="b3", help="an arm to compare run PSNR per group with ('' for none)")
    ap.add_argument("--data-root", type=Path, default=Path("../shared/data"))
    ap.add_argument("--out", type=Path)
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--sh-degree-interval", type=int, default=1000)
    ap.add_argument("--restart-rounds", type=int, nargs="*", default=[],
                    help="rounds to mark in --plot as restarts (restart-at-views 8 16 with 4 initial views: 4 12)")
    ap.add_argument("--title", default="Where the schedule cost lands (tune6, half scale, random + hpgs orders, seeds 0-2)")
    args = ap.parse_args()
    cache: Dict[tuple, dict] = {}
    by_arm = {arm: {start: arm_report(args.root, start, arm, args.other, args.data_root, cache)
                    for start in sorted(p.name for p in args.root.iterdir() if (p / arm).is_dir())}
              for arm in args.arm}
    # one arm: {start: entry} (as before); several: {arm: {start: entry}}
    write_json_atomic(args.out or args.root / "cost_by_view.json", by_arm if len(by_arm) > 1 else by_arm[args.arm[0]])
    if args.plot:
        plot_rounds(by_arm, args.plot, args.sh_degree_interval, args.restart_rounds, args.title)


def plot_rounds(by_arm: Dict[str, dict], path: Path, sh_interval: int, restarts: List[int], title: str) -> None:
    """Mean cost per round of the nearest training view, one line per (arm, start)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hpgs_ns.atomic_write import atomic_path

    fig, ax = plt.subplots(figsize=(8, 4))
    steps: List[int] = []
    lines = [(arm, start, entry) for arm, report in by_arm.items() for start, entry in sorted(report.items())]
    for arm, start, entry in lines:
        rounds = sorted(int(k) for k in entry["cost_by_round"])
        cells = [entry["cost_by_round"][str(k)] for k in rounds]
        ax.errorbar(rounds, [c["mean"] for c in cells], yerr=[c["se"] or 0 for c in cells], marker="o", capsize=3,
                    label=f"{start} start" if len(by_arm) == 1 else f"{arm}, {start} start")
        steps = steps or entry.get("round_steps", [])
    opens = next((k + 1 for k, step in enumerate(steps) if step >= sh_interval), None)  # round k+1 arrives at steps[k]
    if opens is not None:
        ax.axvline(opens - 0.5, color="gray", linestyle="--")
        ax.text(opens - 0.4, ax.get_ylim()[1] * 0.92, f"SH degree 1 opens (step {sh_interval})", color="gray")
    for k, r in enumerate(restarts):
        ax.axvline(r, color="green", linestyle=":", label="restart (restart-at-views)" if k == 0 else None)
    ax.axhline(0, color="black", linewidth=0.5)
    labels = ["initial"] + [f"{k}\n{steps[k - 1]}" if k - 1 < len(steps) else str(k) for k in range(1, 17)]
    ax.set_xticks(range(17), labels, fontsize=7)
    ax.set_xlabel("round that added the test view's nearest training view (and the step it arrived)")
    ax.set_ylabel("final-set − run PSNR (dB)")
    ax.set_title(title)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


if __name__ == "__main__":
    main()
