"""Where the schedule cost lands: the cost of each test view, grouped by when the training view nearest to it (by
camera centre) joined the run, read from a results folder's `cost_by_round.json`.

The grouping needs the captures' camera poses, which a results folder does not hold, so the lab script
`benchmarks/schedule_cost_views.py --out <folder>/cost_by_round.json` computes it beside the captures and the report
only renders what that file says (a folder without the file has no such section).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import List

FILE = "cost_by_round.json"
# (name, first round, last round) of the nearest training view: the file's groups, as the lab script writes them
GROUPS = (("initial", 0, 0), ("rounds 1-8", 1, 8), ("rounds 9-12", 9, 12), ("rounds 13-16", 13, 16))


def cost_by_round_section(out: Path) -> str:
    """Markdown: per start (the file's top-level keys) a table of selectors x groups, mean cost over test views
    (dB) with the number of views; empty without the file."""
    path = out / FILE
    if not path.is_file():
        return ""
    report = json.loads(path.read_text())
    lines: List[str] = [
        "Final-set − run PSNR of each test view (dB), grouped by the round that added the training view nearest to "
        "it (by camera centre; `initial`: one of the initial views), mean over the test views of every run with its "
        f"final-set (views in brackets); from `{FILE}` (`benchmarks/schedule_cost_views.py`, which reads the "
        "captures' poses).", ""]
    for start, entry in sorted(report.items()):
        names = [name for name, _, _ in GROUPS]
        lines += [f"| start | selector | {' | '.join(names)} |", "|---|---|" + "---|" * len(names)]
        rows = sorted(entry.get("cost_by_group_by_selector", {}).items()) + [("all selectors", entry["cost_by_group"])]
        for selector, groups in rows:
            cells = [f"{groups[g]['mean']:+.2f} ({groups[g]['views']})" if g in groups else "–" for g in names]
            lines.append(f"| {start} | {selector} | {' | '.join(cells)} |")
        lines.append("")
    return "\n".join(lines)
