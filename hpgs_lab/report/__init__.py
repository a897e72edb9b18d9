"""`hpgs bench`'s report: tables (`tables`), figures (`plots`), the paired comparisons (`paired`), and the results
page (`write_report`).

Everything here reads the per-run results (`results.load_results`) and writes nothing but tables, figures and
the page, so `hpgs bench --report-only` can rebuild it from any results folder. Which selector beats which is
decided in `paired.md` only (`stats`: runs paired by scene and seed, intervals over scenes); `table.md`'s means
and spreads are for reading. Where runs have final-set references (`hpgs bench --final-set`), `table.md` and the
results page also show each run's schedule cost (`schedule`), and `power.md` how likely the comparisons were to
find a gain of 0.5 or 1 dB (`bench.power`); `hpgs_paper.md` puts protocol-`hpgs` runs beside the HP-GS paper's
table (`paper_table`); `missing.md` names what the folder's grid lacks (`missing`); with both rankings, `paired.md`
ends with the default-selector rule applied to them (`default_rule`); `cost_by_round.md` renders where the schedule
cost lands, from the lab's `cost_by_round.json` (`cost_by_round`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from hpgs_lab.power import power_section
from hpgs_lab.report.cost_by_round import cost_by_round_section
from hpgs_lab.report.default_rule import default_rule_section
from hpgs_lab.report.missing import missing_section
from hpgs_lab.report.paired import comparable, comparison_plan, paired_report, planned_comparisons, verdict_sentence
from hpgs_lab.report.paper_table import hpgs_paper_table
from hpgs_lab.report.plots import camera_map, gain_plot, make_plots, stress_plot
from hpgs_lab.report.schedule import final_set_rows, schedule_cost_table
from hpgs_lab.report.tables import (
    device_counts,
    markdown_table,
    noise_table,
    solo,
    stress_table,
    throughput_table,
    work_table,
)
from hpgs_lab.results import load_final_sets, load_results
from hpgs_ns.atomic_write import write_text_atomic

DEFAULT_RESULTS_PAGE = Path("docs/results.md")
SCHEDULE_TITLE = "**Schedule cost (final-set − run)**"
COST_BY_ROUND_TITLE = "**Schedule cost by when the nearest training view arrived**"
VIEWS_ALONE_TITLE = "### By their views alone (final-sets)"
DEFAULT_RULE_TITLE = "### The default of `ns-train hpgs`"


def write_report(out: Path, results_page: Optional[Path] = None) -> List[Path]:
    """Every table and plot of a results folder, beside its runs; with `results_page`, the results page too.
    Returns the files written."""
    rows = load_results(out)
    written = []
    final_sets = load_final_sets(out)
    schedule = schedule_cost_table(rows, final_sets)
    table = markdown_table(rows) + (f"\n{SCHEDULE_TITLE}\n\n{schedule}" if schedule else "")
    paired = paired_report(rows)
    final_rows = final_set_rows(rows, final_sets)
    views_alone = paired_report(final_rows)
    if views_alone:  # the second ranking: each run's final views trained from step 0, compared the same way
        paired += (f"\n{VIEWS_ALONE_TITLE}\n\nThe same comparisons on the runs' final-sets (each run's final views "
                   "trained from step 0 with its seed): which selector picks the better views, apart from when they "
                   f"arrived.\n\n{views_alone}")
        rule = default_rule_section(rows, final_rows)
        if rule:
            paired += f"\n{DEFAULT_RULE_TITLE}\n\n{rule}"
    sections = {"table.md": table, "paired.md": paired, "missing.md": missing_section(rows, final_sets),
                "work.md": work_table(rows),
                "noise.md": noise_table(rows), "throughput.md": throughput_table(rows), "stress.md": stress_table(rows),
                "cost_by_round.md": cost_by_round_section(out),
                "power.md": power_section(comparable(rows), planned=planned_comparisons(rows)), "hpgs_paper.md": hpgs_paper_table(rows)}
    for name, text in sections.items():
        if text:
            written.append(write_text_atomic(out / name, text))
        else:  # a section now empty (e.g. nothing missing any more) leaves no stale file from an earlier report
            (out / name).unlink(missing_ok=True)
    written += stress_plot(rows, out) + make_plots(rows, out) + gain_plot(rows, out)
    if results_page is not None:
        figures = sorted(out.glob("*-paired-gains.png"))
        written.append(write_text_atomic(results_page, results_page_text(out, {**sections, "schedule": schedule},
                                                                         figures, results_page)))
    return written


def results_section(out: Path, sections: Dict[str, str]) -> str:
    """The comparisons, their power, the schedule cost (with final-set references), repeat noise and throughput of
    a results folder, as markdown with a level-2 heading per part (paired.md's protocol headings become level 3)."""
    parts = [f"Built by `hpgs bench --out {out.as_posix()} --report-only`; every comparison pairs runs by scene and seed.", ""]
    if sections["paired.md"]:
        paired = ("\n" + sections["paired.md"]).replace("\n#### ", "\n### ").lstrip("\n")
        paired = paired.replace(VIEWS_ALONE_TITLE, "## By their views alone (final-sets)")
        paired = paired.replace(DEFAULT_RULE_TITLE, "## The default of `ns-train hpgs`")
        parts += ["## By the runs (views added during training)", "", paired]
    if sections.get("power.md"):
        parts += ["## Power", "", sections["power.md"]]
    if sections.get("missing.md"):
        parts += ["## Runs not in the folder", "", sections["missing.md"], ""]
    elif sections["paired.md"]:
        parts += ["## Runs not in the folder", "", "None: every selector ran on every scene at each seed run there, and, in "
                  "a protocol with final-sets, every run has its own.", ""]
    if sections.get("schedule"):  # `schedule.schedule_cost_table`, where runs have final-set references
        parts += [heading(SCHEDULE_TITLE), "", sections["schedule"]]
    if sections.get("cost_by_round.md"):
        parts += [heading(COST_BY_ROUND_TITLE), "", sections["cost_by_round.md"]]
    if sections.get("hpgs_paper.md"):
        parts += ["## HP-GS's table (protocol `hpgs`), beside the paper's", "", sections["hpgs_paper.md"]]
    for name, title in (("noise.md", "Repeat noise against seed spread"), ("throughput.md", "Throughput")):
        if sections[name]:
            parts += [f"## {title}", "", sections[name]]
    return "\n".join(parts)


def heading(bold_title: str) -> str:
    """A folder page's bold title (`**...**`) as a level-2 heading of the results page."""
    return "## " + bold_title.strip("*")


def results_page_text(out: Path, sections: Dict[str, str], figures: Sequence[Path] = (),
                      page: Optional[Path] = None) -> str:
    """The whole results page: a title, a note that it is generated, each protocol's paired-gains figure (linked
    relative to the page at `page`), and `results_section`."""
    head = ["# Benchmark results: which selector?", "",
            f"<!-- Generated by `hpgs bench --out {out.as_posix()} --report-only --results-page PATH`; edits here are "
            "overwritten. -->", ""]
    for figure in figures:
        link = Path(os.path.relpath(figure, page.parent if page is not None else Path.cwd())).as_posix()
        protocol = figure.name.removesuffix("-paired-gains.png")
        head += [f"![{protocol} protocol: each selector's paired PSNR gain over random, per scene and seed]({link})", ""]
    return "\n".join(head) + "\n" + results_section(out, sections).strip() + "\n"


__all__ = [
    "DEFAULT_RESULTS_PAGE", "camera_map", "comparable", "comparison_plan", "device_counts", "gain_plot",
    "load_results", "make_plots", "markdown_table", "noise_table", "paired_report", "results_page_text",
    "results_section", "schedule_cost_table", "solo", "stress_plot", "stress_table", "throughput_table",
    "verdict_sentence", "work_table", "write_report",
]
