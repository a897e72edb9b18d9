"""The Done-when figures of issue #33 (active training), from the full-scale judging runs.

Reads `benchmarks/results/judge-full/<scene>/<start>/<variant>/seed<k>.json` (start: `colmap` or `active`;
variant: the progressive run's selector, e.g. `farthest`, or `final-set`, its final 20 views trained from step 0), and the runs of
main at 2bbac07 (`benchmarks/results/suite/<scene>/fisherrf/farthest/`) for the guard. Prints per scene and start:
run PSNR per seed, final-set, schedule cost (final-set - run, same seed), then the bars: mean schedule cost with its
95% paired interval (hierarchical bootstrap over scenes, `hpgs_lab.stats`), fox's PSNR, the seed SD of
`farthest` pooled over scenes; and each trainer arm (a start folder such as `colmap-r16`) against another (by default
`colmap`), paired by scene and seed, with its interval and sign-flip p; writes them as JSON. Random runs (bonsai,
fox) live in `<start>-random/` folders beside their own final-sets, and count in their start mode's Done-when line. An arm without final-set
runs of its own (`colmap-r20`) uses its start mode's (`colmap`) when its views do not depend on training (farthest,
random).

    python benchmarks/judge_table.py [--out benchmarks/results/judge-full/summary.json]
    python benchmarks/judge_table.py --root benchmarks/results/tune-full --out benchmarks/results/tune-full/summary.json \
        --compare colmap-r16:colmap random2:random
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path

from hpgs_lab import stats
from hpgs_ns.atomic_write import write_json_atomic

ROOT = Path("benchmarks/results/judge-full")
BEFORE = Path("benchmarks/results/suite")  # main at 2bbac07, same protocol
# final-set of main at 2bbac07 (../shared/design/schedule-pilot.md: fox's farthest views, seeds 0/1, H100)
FINAL_SET_BEFORE = {"fox": {0: 24.00, 1: 24.49}}
# Selectors whose views do not depend on training (same seed, same views): an arm of the trainer (a start folder
# such as `colmap-r20`) then shares its start mode's final-set (`colmap`'s).
VIEWS_WITHOUT_TRAINING = ("farthest", "random")
BARS = {"cost_mean": 0.3, "cost_hi": 0.6, "fox": 23.5, "seed_sd": 0.4}


def load(root: Path):
    """({(scene, start, variant): {seed: test metrics}}, {(scene, start, variant): {seed: (the run's final training
    views, its --extra-args)}})"""
    runs, setup = defaultdict(dict), defaultdict(dict)
    for path in sorted(root.glob("*/*/*/seed*.json")):
        variant, start, scene = path.parent.name, path.parent.parent.name, path.parent.parent.parent.name
        data = json.loads(path.read_text())
        runs[(scene, start, variant)][int(data["seed"])] = data["test"]
        setup[(scene, start, variant)][int(data["seed"])] = (
            frozenset(data.get("initial_views", []) + data.get("chosen_views", [])),
            data.get("provenance", {}).get("settings", {}).get("extra_args", ""))
    return runs, setup


def only_after_add_flags(extra: str, base: str) -> bool:
    """Whether `extra` adds to `base` nothing but `--pipeline.selection.after-add.*` options (and their values)."""
    added = [word for word in extra.split() if word not in set(base.split())]
    return all(not word.startswith("--") or word.startswith("--pipeline.selection.after-add.") for word in added)


def borrowed_final_set(setup, scene: str, start: str, selector: str) -> str:
    """The start folder whose final-set serves an arm without its own: its start mode's (`colmap-r20` -> `colmap`)
    when the selector's views do not depend on training, every seed's final views are the final-set's, and the
    arm differs from its start mode's runs only by after-add options (which act from the first add on, so the
    final-set, trained without adds, is the same run)."""
    base = start.split("-")[0] + ("-random" if start.endswith("-random") else "")  # colmap-r20-random -> colmap-random
    if base == start or selector not in VIEWS_WITHOUT_TRAINING:
        return start
    mine, theirs = setup.get((scene, start, selector), {}), setup.get((scene, base, "final-set"), {})
    same = any(seed in theirs for seed in mine) and all(
        views == theirs[seed][0] for seed, (views, _) in mine.items() if seed in theirs)
    base_extra = next(iter(setup.get((scene, base, selector), {}).values()), (None, ""))[1]
    after_add_only = all(only_after_add_flags(extra, base_extra) for _, extra in mine.values())
    return base if mine and theirs and same and after_add_only else start


def before(scene: str) -> dict:
    out = {}
    for path in sorted((BEFORE / scene / "fisherrf" / "farthest").glob("seed*.json")):
        data = json.loads(path.read_text())
        out[int(data["seed"])] = data["test"]["psnr"]
    return out


def pooled_sd(groups) -> tuple:
    """Pooled within-group SD over groups with >= 2 values, and the degrees of freedom behind it."""
    ss, dof = 0.0, 0
    for values in groups:
        if len(values) >= 2:
            mean = sum(values) / len(values)
            ss += sum((v - mean) ** 2 for v in values)
            dof += len(values) - 1
    return (math.sqrt(ss / dof) if dof else float("nan")), dof


def summarise(runs, setup) -> dict:
    scenes = sorted({k[0] for k in runs})
    starts = sorted({k[1] for k in runs})
    table, summary = [], {"bars": BARS, "starts": {}}
    for start in starts:
        costs, seed_groups = {}, []
        for scene in scenes:
            selectors = sorted(v for (sc, st, v) in runs if sc == scene and st == start and v != "final-set")
            selector = selectors[0] if selectors else "farthest"
            if len(selectors) > 1:  # one final-set folder per start: another selector belongs in <start>-<selector>/
                print(f"warning: {scene}/{start} holds runs of {', '.join(selectors)}; only {selector}'s are read")
            run = {s: t["psnr"] for s, t in runs.get((scene, start, selector), {}).items()}
            final_from = start if (scene, start, "final-set") in runs else borrowed_final_set(setup, scene, start, selector)
            final = {s: t["psnr"] for s, t in runs.get((scene, final_from, "final-set"), {}).items()}
            if not run:
                continue
            for seed, (views, _) in setup.get((scene, final_from, "final-set"), {}).items():
                made = setup.get((scene, start, selector), {}).get(seed)
                if made is not None and made[0] != views:  # a final-set must train its run's final views
                    print(f"warning: {scene}/{final_from}/final-set seed {seed} trained other views than "
                          f"{scene}/{start}/{selector} seed {seed} ended with")
            cost = {s: final[s] - run[s] for s in run if s in final}
            if cost:
                costs[scene] = cost
            seed_groups.append(list(run.values()))
            table.append({"scene": scene, "start": start, "selector": selector, "run": run, "final_set": final, "final_set_of": final_from,
                          "cost": cost,
                          "before_2bbac07": before(scene) if start == "colmap" else {},
                          "final_set_before_2bbac07": FINAL_SET_BEFORE.get(scene, {}) if start == "colmap" else {}})
        entry = {"scenes": sorted(costs), "pairs": sum(len(v) for v in costs.values()),
                 "selectors": sorted({r.get("selector", "") for r in table if r["start"] == start})}
        entry.update(cost_bar(costs))
        sd, dof = pooled_sd(seed_groups)
        entry.update(seed_sd=sd, seed_sd_dof=dof, seed_sd_pass=bool(dof and sd <= BARS["seed_sd"]))
        fox = [r for r in table if r["scene"] == "fox" and r["start"] == start]
        if fox:
            entry["fox"] = fox[0]["run"]
            entry["fox_pass"] = all(v >= BARS["fox"] for v in fox[0]["run"].values())
        summary["starts"][start] = entry
    summary["table"] = table
    summary["modes"] = done_when(table)
    return summary


def cost_bar(costs) -> dict:
    """The schedule-cost figures of {scene: {pair: cost}}: mean of per-scene means, its 95% hierarchical-bootstrap
    interval, and whether #33's bar holds ({} without costs)."""
    if not costs:
        return {}
    mean, lo, hi = stats.hierarchical_bootstrap(dict(costs), n_boot=10000, seed=0)
    return dict(cost_mean=mean, cost_lo=lo, cost_hi=hi, cost_pass=bool(mean <= BARS["cost_mean"] and hi < BARS["cost_hi"]))


def done_when(table) -> dict:
    """#33's bars per start mode, pooled over its selectors: `colmap` with `colmap-random` (the random runs on
    bonsai and fox live in a start folder of their own so that their final-sets do not meet farthest's). Schedule
    cost: every (selector, seed) pair of a scene counts, the bootstrap resamples scenes; fox: every 20-view run;
    seed SD: `farthest` only (the bar's wording)."""
    modes = {}
    for mode in sorted({r["start"] for r in table if "-" not in r["start"]}):
        rows = [r for r in table if r["start"] in (mode, f"{mode}-random")]
        costs = defaultdict(dict)
        for r in rows:
            for seed, cost in r["cost"].items():
                costs[r["scene"]][f"{r['start']}:{seed}"] = cost
        entry = {"starts": sorted({r["start"] for r in rows}), "scenes": sorted(costs),
                 "pairs": sum(len(v) for v in costs.values())}
        entry.update(cost_bar(costs))
        fox = {f"{r['start']}:{seed}": v for r in rows if r["scene"] == "fox" for seed, v in r["run"].items()}
        if fox:
            entry.update(fox=fox, fox_pass=all(v >= BARS["fox"] for v in fox.values()))
        modes[mode] = entry
    return modes


def arm_gains(runs, arm: str, base: str) -> dict:
    """{scene: {seed: PSNR of `arm`'s progressive run - `base`'s with the same selector}} over the (scene, seed)
    pairs both have."""
    gains = defaultdict(dict)
    for (scene, start, variant), by_seed in runs.items():
        if start != arm or variant == "final-set":
            continue
        other = runs.get((scene, base, variant), {})
        for seed, test in by_seed.items():
            if seed in other:
                gains[scene][seed] = test["psnr"] - other[seed]["psnr"]
    return dict(gains)


def compare_arms(runs, pairs) -> list:
    out = []
    for arm, base in pairs:
        gains = arm_gains(runs, arm, base)
        if not gains:
            print(f"{arm} - {base}: no runs of both on the same scene and seed")
            continue
        mean, lo, hi = stats.hierarchical_bootstrap(gains, n_boot=10000, seed=0)
        p = stats.sign_flip_test(list(stats.scene_means(gains).values()), seed=0)
        out.append({"arm": arm, "base": base, "scenes": len(gains), "pairs": sum(len(g) for g in gains.values()),
                    "gain": mean, "lo": lo, "hi": hi, "p": p, "per_scene": stats.scene_means(gains)})
    return out


def fmt(values: dict) -> str:
    return " / ".join(f"{values[s]:.2f}" for s in sorted(values)) or "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT)
    parser.add_argument("--out", type=Path, default=ROOT / "summary.json")
    parser.add_argument("--compare", nargs="*", default=None, metavar="ARM:BASE",
                        help="start folders to pair (default: every start against colmap, random starts against "
                             "colmap-random)")
    args = parser.parse_args()
    runs, setup = load(args.root)
    summary = summarise(runs, setup)
    if args.compare is None:
        starts = sorted({k[1] for k in runs})
        pairs = [(start, "colmap") for start in starts if start != "colmap" and not start.endswith("-random")]
        pairs += [(start, "colmap-random") for start in starts if start.endswith("-random") and start != "colmap-random"]
    else:
        pairs = [tuple(pair.split(":", 1)) for pair in args.compare]
    summary["arms"] = compare_arms(runs, pairs)
    print("| scene | start | farthest (seeds 0 / 1) | final-set | schedule cost | main at 2bbac07: run / final-set |")
    print("|---|---|---|---|---|---|")
    for r in summary["table"]:
        old = fmt(r["before_2bbac07"]) + " / " + fmt(r["final_set_before_2bbac07"]) if r["before_2bbac07"] else "-"
        print(f"| {r['scene']} | {r['start']} | {fmt(r['run'])} | {fmt(r['final_set'])} | "
              f"{' / '.join(f'{v:+.2f}' for v in r['cost'].values()) or '-'} | {old} |")
    print()
    for start, e in summary["starts"].items():
        line = f"{start} ({', '.join(e['selectors'])} only): "
        if "cost_mean" in e:
            line += (f"schedule cost {e['cost_mean']:+.2f} dB [{e['cost_lo']:+.2f}, {e['cost_hi']:+.2f}] "
                     f"({len(e['scenes'])} scenes, {e['pairs']} pairs; bar <= {BARS['cost_mean']}, upper < "
                     f"{BARS['cost_hi']}: {'met' if e['cost_pass'] else 'not met'}); ")
        line += f"seed SD {e['seed_sd']:.2f} dB ({e['seed_sd_dof']} df; bar <= {BARS['seed_sd']}: "
        line += f"{'met' if e['seed_sd_pass'] else 'not met'})"
        if "fox" in e:
            line += f"; fox {fmt(e['fox'])} (bar >= {BARS['fox']}: {'met' if e['fox_pass'] else 'not met'})"
        print(line)
    for mode, e in summary["modes"].items():
        if "cost_mean" not in e or len(e["starts"]) < 2:
            continue  # the same figures as the start's own line above
        line = (f"Done-when, {mode} start ({' + '.join(e['starts'])}): schedule cost {e['cost_mean']:+.2f} dB "
                f"[{e['cost_lo']:+.2f}, {e['cost_hi']:+.2f}] ({len(e['scenes'])} scenes, {e['pairs']} pairs): "
                f"{'met' if e['cost_pass'] else 'not met'}")
        if "fox" in e:
            line += f"; fox {', '.join(f'{k} {v:.2f}' for k, v in sorted(e['fox'].items()))}: "
            line += "met" if e["fox_pass"] else "not met"
        print(line)
    for c in summary["arms"]:
        print(f"{c['arm']} - {c['base']}: {c['gain']:+.2f} dB [{c['lo']:+.2f}, {c['hi']:+.2f}], sign-flip p = {c['p']:.3f} "
              f"({c['scenes']} scenes, {c['pairs']} pairs; per scene " +
              ", ".join(f"{k} {v:+.2f}" for k, v in c["per_scene"].items()) + ")")
    write_json_atomic(args.out, summary)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
