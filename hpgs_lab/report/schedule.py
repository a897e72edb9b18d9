"""The schedule cost: what adding views during training costs against having had them from step 0.

A run's `final-set` reference (`hpgs bench --final-set`) trains the run's final views (initial and chosen) from
step 0 with its seed and steps and no rounds. Its test PSNR minus the run's is the run's *schedule cost* in dB:
positive when the same views would have done better from the start, i.e. what the schedule of late additions
costs, apart from which views were picked. Pairs are (scene, protocol, selector, seed), first repeats only; a
final-set whose recorded views are not its run's final views (the run was re-run since) is left out.

Per scene and selector: the run's and the final-set's PSNR and their difference, means over the paired seeds,
beside the `initial` and `all` references of those seeds. Across scenes (no smoke-check scenes, no stress
copies): the mean of per-scene mean costs with a 95% hierarchical bootstrap interval (`stats`), as the paired
comparisons are made; and the selectors ranked twice on the scenes every one of them has pairs on, by their runs
and by their final-sets (the views alone): a trainer that ranks selectors by when their views arrived shows up as
two different orders.
"""

from __future__ import annotations

import dataclasses
from typing import Dict, List, NamedTuple, Sequence, Tuple

from hpgs_lab import stats
from hpgs_lab.names import ALL, INITIAL
from hpgs_lab.report.paired import comparable
from hpgs_lab.report.tables import bench_order
from hpgs_lab.results import RunResult


class SchedulePair(NamedTuple):
    """A selector run and its final-set reference."""

    run: RunResult
    final: RunResult

    @property
    def cost(self) -> float:
        """Final-set PSNR - run PSNR (dB)."""
        return self.final.test.psnr - self.run.test.psnr


def schedule_pairs(rows: Sequence[RunResult], final_sets: Sequence[RunResult]) -> Tuple[List[SchedulePair], int]:
    """(each first-repeat run with its current final-set, the number of final-sets left out as stale: their
    recorded views are not their run's final views). Final-sets without their run are left out silently."""
    runs = {(r.scene, r.protocol, r.selector, r.seed, r.repeat): r for r in rows if not r.is_reference}
    pairs, stale = [], 0
    for f in final_sets:
        source = f.final_set_of
        if source is None or source.repeat:
            continue
        run = runs.get((f.scene, f.protocol, source.selector, source.seed, source.repeat))
        if run is None:
            continue
        if sorted(source.views) != run.final_views:
            stale += 1
            continue
        pairs.append(SchedulePair(run, f))
    return pairs, stale


def final_set_rows(rows: Sequence[RunResult], final_sets: Sequence[RunResult]) -> List[RunResult]:
    """Each current final-set as a row of its run's selector (same scene, protocol and seed), so the paired
    comparisons can rank the selectors by their views alone."""
    pairs, _ = schedule_pairs(rows, final_sets)
    return [dataclasses.replace(p.final, selector=p.run.selector) for p in pairs]


def _mean(values: Sequence[float]) -> float:
    return sum(values) / len(values)


def schedule_cost_table(rows: Sequence[RunResult], final_sets: Sequence[RunResult]) -> str:
    """The per-scene table and the across-scenes table of the schedule cost, as markdown ("" without a pair)."""
    pairs, stale = schedule_pairs(rows, final_sets)
    note = [f"{stale} final-set result(s) left out: their run has other views now (re-run the sweep with `--final-set` "
            "to redo them)."] if stale else []
    if not pairs:
        return "\n".join(note) + "\n" if note else ""
    order = bench_order()
    groups: Dict[Tuple[str, str, str], List[SchedulePair]] = {}
    for p in pairs:
        groups.setdefault((p.run.scene, p.run.protocol, p.run.selector), []).append(p)
    references = {(r.scene, r.protocol, r.selector, r.seed): r.test.psnr for r in rows if r.selector in (INITIAL, ALL)
                  and not r.repeat}
    lines = [
        "Schedule cost: test PSNR (dB) of each run's final views trained from step 0 (`final-set`), minus the run's; "
        "positive: the same views from the start do better. Means over the seeds with both; `initial` and `all` "
        "over those of the same seeds that ran them (their count in brackets where fewer).",
        "",
        "| scene | protocol | selector | seeds | views | run PSNR | final-set PSNR | schedule cost | initial PSNR | all PSNR |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (scene, protocol, sel), group in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], order.get(kv[0][2], 99), kv[0][2])):
        group = sorted(group, key=lambda p: p.run.seed)
        views = sorted({p.run.num_views_final for p in group})
        view_cell = str(views[0]) if len(views) == 1 else f"{views[0]}-{views[-1]}"
        cells = []
        for ref in (INITIAL, ALL):
            values = [references[scene, protocol, ref, p.run.seed] for p in group if (scene, protocol, ref, p.run.seed) in references]
            cell = f"{_mean(values):.2f}" if values else "–"
            cells.append(cell + (f" ({len(values)})" if values and len(values) < len(group) else ""))
        lines.append(
            f"| {scene} | {protocol} | {sel} | {len(group)} | {view_cell} | {_mean([p.run.test.psnr for p in group]):.2f} | "
            f"{_mean([p.final.test.psnr for p in group]):.2f} | {_mean([p.cost for p in group]):+.2f} | {' | '.join(cells)} |"
        )
    ranks = rankings_table(pairs)
    lines += ["", across_scenes_table(pairs)] + (["", ranks] if ranks else []) + ([""] + note if note else [])
    return "\n".join(lines) + "\n"


def cost_by_scene(pairs: Sequence[SchedulePair], protocol: str, selector: str) -> stats.Gains:
    """scene -> {seed: schedule cost} of one protocol and selector, comparable scenes only (`paired.comparable`)."""
    keep = {id(r) for r in comparable([p.run for p in pairs])}
    out: stats.Gains = {}
    for p in pairs:
        if id(p.run) in keep and (p.run.protocol, p.run.selector) == (protocol, selector):
            out.setdefault(p.run.scene, {})[p.run.seed] = p.cost
    return out


def selector_costs(pairs: Sequence[SchedulePair], protocol: str) -> Dict[str, stats.Gains]:
    """selector -> `cost_by_scene` for one protocol's selectors that have pairs on comparable scenes, in the
    benchmark's order."""
    order = bench_order()
    selectors = sorted({p.run.selector for p in pairs if p.run.protocol == protocol}, key=lambda s: (order.get(s, 99), s))
    return {sel: c for sel in selectors if (c := cost_by_scene(pairs, protocol, sel))}


def pooled_cost_by_scene(by_selector: Sequence[stats.Gains]) -> stats.Gains:
    """scene -> {k: schedule cost}: several selectors' `cost_by_scene` pooled, a scene's (selector, seed) pairs
    numbered in turn, so the bootstrap resamples them as it resamples one selector's seeds."""
    out: stats.Gains = {}
    for costs in by_selector:
        for scene, by_seed in costs.items():
            cell = out.setdefault(scene, {})
            for cost in by_seed.values():
                cell[len(cell)] = cost
    return out


def across_scenes_table(pairs: Sequence[SchedulePair], n_boot: int = 10000, seed: int = 0) -> str:
    """Per protocol and selector: the mean over scenes of per-scene mean schedule costs, with its 95% hierarchical
    bootstrap interval (scenes, then seeds within a scene; "n/a" with fewer than two scenes); where a protocol has
    two or more selectors, a row `all selectors` pools them (per scene, the mean over every selector's pairs): the schedule
    cost of the trainer rather than of one selector's order."""
    lines = ["Across scenes (no smoke-check scenes or stress copies): mean of per-scene mean schedule costs (dB), "
             "95% hierarchical bootstrap interval.", "",
             "| protocol | selector | scenes | pairs | schedule cost | 95% CI |", "|---|---|---|---|---|---|"]

    def row(protocol: str, name: str, costs: Dict[str, Dict[int, float]]) -> str:
        estimate, lo, hi = stats.hierarchical_bootstrap(costs, n_boot=n_boot, seed=seed)
        interval = f"[{lo:+.2f}, {hi:+.2f}]" if len(costs) > 1 else "n/a (1 scene)"
        n_pairs = sum(len(c) for c in costs.values())
        return f"| {protocol} | {name} | {len(costs)} | {n_pairs} | {estimate:+.2f} | {interval} |"

    header = len(lines)
    for protocol in sorted({p.run.protocol for p in pairs}):
        costs = selector_costs(pairs, protocol)
        lines += [row(protocol, sel, c) for sel, c in costs.items()]
        if len(costs) > 1:
            lines.append(row(protocol, "all selectors", pooled_cost_by_scene(list(costs.values()))))
    if len(lines) == header:
        return "Across scenes: no final-set pairs outside smoke-check scenes and stress copies."
    return "\n".join(lines)


def rankings_table(pairs: Sequence[SchedulePair]) -> str:
    """Per protocol with two or more selectors: each selector's mean run PSNR and mean final-set PSNR over the
    scenes all of them have pairs on (mean over scenes of per-scene means over seeds; comparable scenes only) and
    its rank by each (1: highest). "" where no protocol has two selectors with a scene in common."""
    keep = {id(r) for r in comparable([p.run for p in pairs])}
    cells: Dict[Tuple[str, str, str], List[SchedulePair]] = {}
    for p in pairs:
        if id(p.run) in keep:
            cells.setdefault((p.run.protocol, p.run.selector, p.run.scene), []).append(p)
    order = bench_order()
    blocks = []
    for protocol in sorted({k[0] for k in cells}):
        selectors = sorted({k[1] for k in cells if k[0] == protocol}, key=lambda s: (order.get(s, 99), s))
        scenes = set.intersection(*({k[2] for k in cells if k[:2] == (protocol, s)} for s in selectors))
        if len(selectors) < 2 or not scenes:
            continue
        means = {}
        for sel in selectors:
            per_scene = [cells[protocol, sel, scene] for scene in sorted(scenes)]
            means[sel] = (_mean([_mean([p.run.test.psnr for p in g]) for g in per_scene]),
                          _mean([_mean([p.final.test.psnr for p in g]) for g in per_scene]))
        rank = [{sel: 1 + sorted(means, key=lambda s: -means[s][i]).index(sel) for sel in selectors} for i in (0, 1)]
        for sel in selectors:
            blocks.append(f"| {protocol} | {sel} | {len(scenes)} | {means[sel][0]:.2f} | {rank[0][sel]} | "
                          f"{means[sel][1]:.2f} | {rank[1][sel]} |")
    if not blocks:
        return ""
    return "\n".join(["Two rankings, on the scenes every selector of the protocol has final-set pairs on: by the runs "
                      "(views added during training) and by the final-sets (the same views from step 0). Mean over "
                      "those scenes of per-scene mean test PSNR (dB); rank 1 is the highest. Read the intervals of "
                      "the paired comparisons before a rank.", "",
                      "| protocol | selector | scenes | run PSNR | rank by run | final-set PSNR | rank by final-set |",
                      "|---|---|---|---|---|---|---|", *blocks])
