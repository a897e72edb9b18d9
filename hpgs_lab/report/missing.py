"""What a results folder lacks: the runs and final-sets its own grid implies but that have no result (failed,
stopped or never started), listed on the results page so a reader knows what the comparisons could not use.

The grid is read from the results themselves, per protocol: every selector run there (references aside), on every
scene at every seed some selector ran on that scene (a scene's extra seeds, given to all its selectors, count
there only). Final-sets: where a protocol has any, every first-repeat run should have a current one.
"""

from __future__ import annotations

from typing import Dict, List, Sequence, Set, Tuple

from hpgs_lab.report.paired import comparable
from hpgs_lab.report.schedule import schedule_pairs
from hpgs_lab.report.tables import bench_order
from hpgs_lab.results import RunResult

LISTED = 30
"""At most this many cells are named per protocol and kind; the rest are counted."""


def missing_cells(rows: Sequence[RunResult], final_sets: Sequence[RunResult]) -> Dict[str, Dict[str, List[Tuple[str, str, int]]]]:
    """protocol -> {"runs": [(scene, selector, seed)], "final-sets": [...]} of what the grid lacks."""
    runs = [r for r in comparable(rows) if not r.is_reference]
    with_final = {(p.run.scene, p.run.protocol, p.run.selector, p.run.seed) for p in schedule_pairs(rows, final_sets)[0]}
    protocols_with_finals = {f.protocol for f in final_sets}
    order = bench_order()
    out: Dict[str, Dict[str, List[Tuple[str, str, int]]]] = {}
    for protocol in sorted({r.protocol for r in runs}):
        group = [r for r in runs if r.protocol == protocol]
        selectors = sorted({r.selector for r in group}, key=lambda s: (order.get(s, 99), s))
        seeds: Dict[str, Set[int]] = {}
        for r in group:
            seeds.setdefault(r.scene, set()).add(r.seed)
        have = {(r.scene, r.selector, r.seed) for r in group}
        grid = [(scene, sel, seed) for scene in sorted(seeds) for sel in selectors for seed in sorted(seeds[scene])]
        lacking = {"runs": [cell for cell in grid if cell not in have]}
        if protocol in protocols_with_finals:
            lacking["final-sets"] = [cell for cell in grid if cell in have
                                     and (cell[0], protocol, cell[1], cell[2]) not in with_final]
        if any(lacking.values()):
            out[protocol] = lacking
    return out


def missing_section(rows: Sequence[RunResult], final_sets: Sequence[RunResult]) -> str:
    """Markdown: per protocol, the runs and final-sets the grid lacks ("" when nothing is missing)."""
    lines: List[str] = []
    for protocol, kinds in missing_cells(rows, final_sets).items():
        for kind, cells in kinds.items():
            if not cells:
                continue
            named = ", ".join(f"{scene}/{sel}/seed{seed}" for scene, sel, seed in cells[:LISTED])
            more = f" and {len(cells) - LISTED} more" if len(cells) > LISTED else ""
            lines.append(f"- {protocol} protocol, {len(cells)} {kind if len(cells) > 1 else kind[:-1]} missing: "
                         f"{named}{more}.")
    if not lines:
        return ""
    return "\n".join(["The grid these results imply (per protocol: every selector on every scene at every seed run "
                      "there), less what has a result. The comparisons above pair only what exists.", "", *lines])
