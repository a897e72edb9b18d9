"""Issue #46's Done-when, read from results folders: is the schedule cost of the trainer small for every selector?

For each FOLDER (a `hpgs bench` results folder with a final-set for its runs), FisherRF protocol: the schedule cost
(final-set - run PSNR) per selector and pooled over the selectors (`all selectors`: per scene the mean of every
selector's pairs), each as the mean over scenes with its 95% hierarchical-bootstrap interval, exactly as the
report's across-scenes table computes them (`hpgs_lab.report.schedule`). The bar: pooled mean at most +0.3 dB, its
interval's upper end below +0.6, every selector's mean at most +0.5.

With `--against BASE` (the trainer a mechanism is judged against, e.g. `benchmarks/results/real12`), also the run
PSNR FOLDER - BASE paired by (scene, selector, seed), on the pairs whose runs differ (a run copied from BASE, as fox
in docs/lab/seeded-restarts-judge-plan.md, is left out: the mechanism did not touch it), its bar `--min-run-gain`
(-0.2 dB), and the mean run wall of each, whose ratio is read against the lease loads (#46's guard: at most +10%);
with `--also-over SCENE ...`, the run PSNR gain again over those scenes alone (a pilot rule's subset); the
schedule cost FOLDER - BASE paired by run, with its interval (what a rule comparing two arms' costs reads); per
selector, the run and final-set PSNR gains apart; and the final-sets both folders trained on the same views
(`random`'s and `farthest`'s, whose views do not depend on training): where a mechanism does not act on final-sets
these are replicates, so their difference is the trainer's run-to-run noise, and each selector's cost is given
again against the mean of both (read beside the cost, not bars). Where the runs recorded each test view's render depth,
also the views nearer in the run than in its final-set (`near_views`: 10th-percentile depth below 0.8x, the
signature of Gaussians floating in front of that camera) and their share of the PSNR the runs lose; where they
recorded what lies in front of each test camera (`front_*`), that too, for the near views, the same views in the
final-sets, and the rest.

    python benchmarks/done_when_46.py benchmarks/results/real6-seeded-restarts --against benchmarks/results/real12 \
        [--also-over SCENE ...] [--out FILE.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from statistics import mean, median, stdev
from typing import Dict, List, Optional, Sequence

from hpgs_lab import stats
from hpgs_lab.report.schedule import pooled_cost_by_scene, schedule_pairs, selector_costs
from hpgs_lab.results import RunResult, load_final_sets, load_results
from hpgs_ns.atomic_write import write_json_atomic

PROTOCOL = "fisherrf"
MEAN_BAR, UPPER_BAR, SELECTOR_BAR = 0.3, 0.6, 0.5


def interval(gains: stats.Gains) -> dict:
    """Mean over scenes of per-scene means, 95% hierarchical-bootstrap interval, sign-flip p, counts."""
    return stats.across_scenes(gains)


def runs_of(folder: Path) -> List[RunResult]:
    return [r for r in load_results(folder) if r.protocol == PROTOCOL and not r.is_reference and not r.repeat]


def done_when(rows: Sequence[RunResult], final_sets: Sequence[RunResult]) -> dict:
    """Per-selector and pooled schedule cost, and whether #46's bar holds."""
    costs = selector_costs(schedule_pairs(rows, final_sets)[0], PROTOCOL)
    if not costs:
        raise SystemExit("done_when_46: no FisherRF run with its final-set here")
    out = {"selectors": {s: interval(c) for s, c in costs.items()},
           "all selectors": interval(pooled_cost_by_scene(list(costs.values())))}
    pooled = out["all selectors"]
    out["met"] = bool(pooled["mean"] <= MEAN_BAR and pooled["hi"] < UPPER_BAR
                      and all(v["mean"] <= SELECTOR_BAR for v in out["selectors"].values()))
    return out


def against(rows: Sequence[RunResult], base: Sequence[RunResult], min_gain: float,
            scenes: Optional[Sequence[str]] = None) -> Optional[dict]:
    """Run PSNR rows - base paired by (scene, selector, seed), runs that differ only (of `scenes`, if given); mean
    walls."""
    by_key = {(r.scene, r.selector, r.seed): r for r in base}
    gains: stats.Gains = {}
    walls: Dict[str, List[float]] = {"folder": [], "base": []}
    for r in rows:
        b = by_key.get((r.scene, r.selector, r.seed))
        if b is None or (r.test.psnr == b.test.psnr and r.chosen_views == b.chosen_views):  # a copy of BASE's run
            continue
        if scenes is not None and r.scene not in scenes:
            continue
        cell = gains.setdefault(r.scene, {})
        cell[len(cell)] = r.test.psnr - b.test.psnr
        walls["folder"].append(float(r.timing.wall_seconds))
        walls["base"].append(float(b.timing.wall_seconds))
    if not gains:
        return None
    gain = interval(gains)
    wall = {k: mean(v) for k, v in walls.items()}
    return {"run_gain": gain, "min_run_gain": min_gain, "run_gain_met": bool(gain["mean"] >= min_gain),
            "mean_wall_s": wall, "wall_ratio": wall["folder"] / wall["base"]}


def cost_difference(rows: Sequence[RunResult], base: Sequence[RunResult], final_sets: Sequence[RunResult],
                    base_final_sets: Sequence[RunResult]) -> Optional[dict]:
    """Schedule cost FOLDER - BASE, each run against its own final-set, paired by (scene, selector, seed): a pilot
    rule that compares two arms' costs reads this interval, not the two means alone."""
    base_cost = {(p.run.scene, p.run.selector, p.run.seed): p.final.test.psnr - p.run.test.psnr
                 for p in schedule_pairs(base, base_final_sets)[0]}
    gains: stats.Gains = {}
    for pair in schedule_pairs(rows, final_sets)[0]:
        b = base_cost.get((pair.run.scene, pair.run.selector, pair.run.seed))
        if b is not None:
            cell = gains.setdefault(pair.run.scene, {})
            cell[len(cell)] = pair.final.test.psnr - pair.run.test.psnr - b
    return interval(gains) if gains else None


def selector_gains(rows: Sequence[RunResult], base: Sequence[RunResult], final_sets: Sequence[RunResult],
                   base_final_sets: Sequence[RunResult]) -> Dict[str, dict]:
    """Per selector, run PSNR and final-set PSNR FOLDER - BASE, paired by (scene, selector, seed): read beside the
    cost, since a mechanism that changes the renders changes the views of the selectors that read them (`hpgs`,
    `fisher`), so their cost moves with their final-sets as well as with the trainer."""
    def run_key(r: RunResult) -> tuple:
        return (r.scene, r.selector, r.seed)

    def final_set_key(r: RunResult) -> tuple:
        return (r.scene, r.final_set_of.selector, r.final_set_of.seed)

    out: Dict[str, dict] = {}
    for part, these, those, key in (("run", rows, base, run_key), ("final_set", final_sets, base_final_sets, final_set_key)):
        by_key = {key(r): r for r in those}
        gains: Dict[str, stats.Gains] = {}
        for r in these:
            b = by_key.get(key(r))
            if b is not None:
                cell = gains.setdefault(key(r)[1], {}).setdefault(r.scene, {})
                cell[len(cell)] = r.test.psnr - b.test.psnr
        for selector, g in gains.items():
            out.setdefault(selector, {})[part] = interval(g)
    return out


def replicate_final_sets(final_sets: Sequence[RunResult], base_final_sets: Sequence[RunResult]) -> Dict[str, dict]:
    """Per selector, the final-sets FOLDER and BASE trained on the same views, paired by (scene, seed): FOLDER - BASE
    PSNR (interval), the SD of that difference, and the largest gap on one test view; with every other setting the
    same these are replicates, and their spread is the noise a pilot's pairs carry."""
    def key(r: RunResult) -> tuple:
        return (r.scene, r.final_set_of.selector, r.final_set_of.seed, tuple(sorted(r.final_set_of.views)))

    by_key = {key(r): r for r in base_final_sets}
    pairs: Dict[str, list] = {}
    for r in final_sets:
        b = by_key.get(key(r))
        if b is not None:
            pairs.setdefault(r.final_set_of.selector, []).append((r, b))
    out: Dict[str, dict] = {}
    for selector, these in pairs.items():
        gains: stats.Gains = {}
        worst = (0.0, "")
        for r, b in these:
            cell = gains.setdefault(r.scene, {})
            cell[len(cell)] = r.test.psnr - b.test.psnr
            base_view = {v.name: v for v in b.test_views}
            for v in r.test_views:
                w = base_view.get(v.name)
                if w is not None and abs(v.psnr - w.psnr) > abs(worst[0]):
                    depths = (f"; depth p10 {v.depth_p10:.3g} here, {w.depth_p10:.3g} there"
                              if v.depth_p10 is not None and w.depth_p10 is not None else "")
                    worst = (v.psnr - w.psnr, f"{r.scene} seed{r.final_set_of.seed} {v.name}{depths}")
        diffs = [d for cell in gains.values() for d in cell.values()]
        out[selector] = {**interval(gains), "sd": stdev(diffs) if len(diffs) > 1 else 0.0,
                         "worst_view_gap": worst[0], "worst_view": worst[1],
                         "keys": [key(r)[:3] for r, _ in these]}
    return out


def cost_against_both(rows: Sequence[RunResult], base: Sequence[RunResult], final_sets: Sequence[RunResult],
                      base_final_sets: Sequence[RunResult], keys: Sequence[tuple]) -> Dict[str, float]:
    """Mean schedule cost of FOLDER's and BASE's runs at `keys` (scene, selector, seed) against the mean of both
    final-sets there: the same reference for both, so the noise of one replicate does not move one arm's cost."""
    def by(runs: Sequence[RunResult], final: bool) -> dict:
        return {((r.scene, r.final_set_of.selector, r.final_set_of.seed) if final else (r.scene, r.selector, r.seed)): r
                for r in runs}

    run, base_run, fs, base_fs = by(rows, False), by(base, False), by(final_sets, True), by(base_final_sets, True)
    keys = [k for k in keys if k in run and k in base_run]
    if not keys:
        return {}
    ref = {k: (fs[k].test.psnr + base_fs[k].test.psnr) / 2 for k in keys}
    return {"folder": mean(ref[k] - run[k].test.psnr for k in keys),
            "base": mean(ref[k] - base_run[k].test.psnr for k in keys), "pairs": len(keys)}


NEAR_RATIO = 0.8


def near_views(rows: Sequence[RunResult], final_sets: Sequence[RunResult], ratio: float = NEAR_RATIO) -> dict:
    """Each run's test views against the same views in its final-set, where both recorded depth: how many are
    nearer in the run (depth_p10 below `ratio` x the final-set's), their mean run - final-set PSNR, the rest's, and
    the mean cost over pairs as recorded and as it would be with the near views at their final-set's PSNR; also per
    start (`seed_points`)."""
    near, rest, by_start, without = [], [], {}, []
    fronts: Dict[str, list] = {"near": [], "rest": [], "near, final-set": []}
    for pair in schedule_pairs(rows, final_sets)[0]:
        final_view = {v.name: v for v in pair.final.test_views}
        start = by_start.setdefault(pair.run.seed_points or "unknown", {"pairs": 0, "near": 0, "views": 0, "cost": []})
        counted, lost = False, 0.0
        for v in pair.run.test_views:
            w = final_view.get(v.name)
            if w is None or v.depth_p10 is None or w.depth_p10 is None:
                continue
            counted = True
            is_near = v.depth_p10 < ratio * w.depth_p10
            (near if is_near else rest).append(v.psnr - w.psnr)
            fronts["near" if is_near else "rest"].append(v)
            if is_near:
                fronts["near, final-set"].append(w)
            lost += (w.psnr - v.psnr) if is_near else 0.0
            start["near"] += int(is_near)
            start["views"] += 1
        if counted:
            start["pairs"] += 1
            cost = pair.final.test.psnr - pair.run.test.psnr
            start["cost"].append(cost)
            without.append(cost - lost / len(pair.run.test_views))
    if not near and not rest:
        return {}
    costs = [c for v in by_start.values() for c in v["cost"]]
    by_start = {k: {"pairs": v["pairs"], "near": v["near"], "views": v["views"], "cost": mean(v["cost"])}
                for k, v in by_start.items() if v["pairs"]}
    out = {"ratio": ratio, "views": len(near) + len(rest), "near": len(near),
           "near_mean": mean(near) if near else 0.0, "rest_mean": mean(rest) if rest else 0.0,
           "cost": mean(costs), "cost_near_as_final_set": mean(without), "by_start": by_start}
    front = {k: front_summary(v) for k, v in fronts.items()}
    if any(front.values()):
        out["front"] = {k: v for k, v in front.items() if v}
    return out


def front_summary(views: Sequence) -> dict:
    """What lies in front of these test cameras (`front_*`, where the runs recorded it): the mean opacity the
    Gaussians in front render over the image, the share of views with a large Gaussian in front, the mean count of
    large ones, the median of their largest sigma, and the mean shares of them on one, and on two or more, training
    views' surfaces, in a training view's image, and flagged by the floater guard's test from a training-split
    camera. {} where no view recorded it."""
    seen = [v for v in views if v.front_large is not None]
    if not seen:
        return {}
    with_large = [v for v in seen if v.front_large]
    two = [v.front_large_on_two_surfaces for v in with_large if v.front_large_on_two_surfaces is not None]
    in_view = [v.front_large_in_view for v in with_large if v.front_large_in_view is not None]
    suspect = [v.front_large_suspect for v in with_large if v.front_large_suspect is not None]
    covers = [v.front_cover for v in seen if v.front_cover is not None]
    return {"views": len(seen), "cover_mean": mean(covers) if covers else None,
            "with_large": len(with_large) / len(seen), "large_mean": mean(v.front_large for v in seen),
            "sigma_max_median": median([v.front_large_sigma_max for v in with_large]) if with_large else None,
            "on_surface_mean": mean(v.front_large_on_surface for v in with_large) if with_large else None,
            "on_two_surfaces_mean": mean(two) if two else None, "in_view_mean": mean(in_view) if in_view else None,
            "suspect_mean": mean(suspect) if suspect else None}


def culled_counts(rows: Sequence[RunResult], final_sets: Sequence[RunResult]) -> Dict[str, dict]:
    """`near_culled` (Gaussians near-cull-screen removed) over the runs and over the final-sets that recorded it."""
    out = {}
    for name, results in (("runs", rows), ("final-sets", final_sets)):
        counts = [r.near_culled for r in results if r.near_culled is not None]
        if counts:
            out[name] = {"mean": mean(counts), "min": min(counts), "max": max(counts), "runs": len(counts)}
    return out


def line(name: str, v: dict) -> str:
    return f"  {name:>14}: {v['mean']:+.2f} dB [{v['lo']:+.2f}, {v['hi']:+.2f}] ({v['scenes']} scenes, {v['pairs']} pairs)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", type=Path, nargs="+")
    ap.add_argument("--against", type=Path, help="results folder of the trainer the folders are judged against")
    ap.add_argument("--min-run-gain", type=float, default=-0.2)
    ap.add_argument("--also-over", nargs="+", metavar="SCENE",
                    help="with --against, the run PSNR gain again over these scenes alone (a pilot rule's subset)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    base = runs_of(args.against) if args.against else None
    base_finals = load_final_sets(args.against) if args.against else None
    report = {}
    for folder in args.folders:
        rows, finals = runs_of(folder), load_final_sets(folder)
        out = done_when(rows, finals)
        print(f"== {folder}: schedule cost, FisherRF protocol")
        for s, v in out["selectors"].items():
            print(line(s, v) + ("" if v["mean"] <= SELECTOR_BAR else f"  > {SELECTOR_BAR}"))
        print(line("all selectors", out["all selectors"]))
        print(f"  Done-when (mean <= {MEAN_BAR}, upper < {UPPER_BAR}, each selector <= {SELECTOR_BAR}): "
              f"{'met' if out['met'] else 'not met'}")
        near = near_views(rows, finals)
        if near:
            out["near_views"] = near
            print(f"  views nearer in the run than in its final-set (depth p10 < {near['ratio']}x): {near['near']} of "
                  f"{near['views']}, run - final-set {near['near_mean']:+.2f} dB (the rest {near['rest_mean']:+.2f}); "
                  f"mean cost over pairs {near['cost']:+.2f} dB, {near['cost_near_as_final_set']:+.2f} with the near "
                  f"views at their final-set's PSNR")
            for start, v in sorted(near["by_start"].items()):
                print(f"    start {start}: {v['pairs']} pairs, cost {v['cost']:+.2f} dB, near views {v['near']} of {v['views']}")
            for which, f in near.get("front", {}).items():
                sigma = "-" if f["sigma_max_median"] is None else f"{f['sigma_max_median']:.3g}"
                surface = "-" if f["on_surface_mean"] is None else f"{f['on_surface_mean']:.2f}"
                if f["on_two_surfaces_mean"] is not None:
                    surface += f" (two or more: {f['on_two_surfaces_mean']:.2f})"
                cover = "" if f["cover_mean"] is None else f"they cover {f['cover_mean']:.0%} of the image; "
                print(f"    in front of the camera, {which} views ({f['views']}): {cover}{f['with_large']:.0%} with a large "
                      f"Gaussian, {f['large_mean']:.1f} large on average, their largest sigma (median) {sigma}, "
                      f"on a training view's surface {surface}"
                      + ("" if f["in_view_mean"] is None else f", in a training view's image {f['in_view_mean']:.2f}")
                      + ("" if f["suspect_mean"] is None else f", the guard's suspects {f['suspect_mean']:.2f}"))
        culled = culled_counts(rows, finals)
        if culled:
            out["near_culled"] = culled
            print("  near-cull-screen removed, mean per run: " + "; ".join(
                f"{k} {v['mean']:.0f} (range {v['min']}-{v['max']}, {v['runs']} runs)" for k, v in culled.items()))
        if base is not None:
            vs = against(rows, base, args.min_run_gain)
            out["against"] = {"base": str(args.against), **(vs or {})}
            if vs:
                g = vs["run_gain"]
                print(f"  run PSNR - {args.against}: {g['mean']:+.2f} dB [{g['lo']:+.2f}, {g['hi']:+.2f}], p {g['p']:.3f} "
                      f"({g['pairs']} pairs that differ; bar >= {args.min_run_gain:+.2f}: "
                      f"{'met' if vs['run_gain_met'] else 'not met'}); mean wall {vs['mean_wall_s']['folder']:.0f} s "
                      f"against {vs['mean_wall_s']['base']:.0f} s (x{vs['wall_ratio']:.3f}, read with the leases' loads)")
                if args.also_over:
                    sub = against(rows, base, args.min_run_gain, scenes=args.also_over)
                    out["against"]["over_scenes"] = {"scenes": list(args.also_over), **(sub or {})}
                    if sub:
                        g = sub["run_gain"]
                        print(f"  over {' '.join(args.also_over)}: {g['mean']:+.2f} dB [{g['lo']:+.2f}, {g['hi']:+.2f}], "
                              f"p {g['p']:.3f} ({g['pairs']} pairs)")
            else:
                print(f"  no run here differs from one in {args.against}")
            diff = cost_difference(rows, base, finals, base_finals)
            if diff:
                out["against"]["cost_difference"] = diff
                print(f"  schedule cost - {args.against}'s, paired by run: {diff['mean']:+.2f} dB [{diff['lo']:+.2f}, "
                      f"{diff['hi']:+.2f}], p {diff['p']:.3f} ({diff['pairs']} pairs)")
            per = selector_gains(rows, base, finals, base_finals)
            out["against"]["by_selector"] = per
            for selector, parts in sorted(per.items()):
                print(f"  {selector} - {args.against}: " + "; ".join(
                    f"{part.replace('_', '-')} {v['mean']:+.2f} dB [{v['lo']:+.2f}, {v['hi']:+.2f}] ({v['pairs']} pairs)"
                    for part, v in parts.items()))
            reps = replicate_final_sets(finals, base_finals)
            for selector, v in sorted(reps.items()):
                both = cost_against_both(rows, base, finals, base_finals, v.pop("keys"))
                v["cost_against_both"] = both
                print(f"  {selector} final-sets on the same views here and in {args.against} (replicates if nothing "
                      f"acts on final-sets): {v['mean']:+.2f} dB [{v['lo']:+.2f}, {v['hi']:+.2f}] ({v['pairs']} pairs), "
                      f"SD {v['sd']:.2f} dB, largest gap on one view {v['worst_view_gap']:+.1f} dB ({v['worst_view']})"
                      + (f"; cost against their mean: here {both['folder']:+.2f}, base {both['base']:+.2f}" if both else ""))
            out["against"]["replicate_final_sets"] = reps
        report[str(folder)] = out
    if args.out:
        write_json_atomic(args.out, report)


if __name__ == "__main__":
    main()
