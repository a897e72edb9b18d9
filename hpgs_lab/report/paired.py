"""Which selector to use: paired comparisons per protocol (`stats`), their tables and the verdicts in words.

Runs are paired by scene and seed, intervals are over scenes; the comparisons are planned before any gain is
seen (`comparison_plan`).
"""

from __future__ import annotations

from typing import List, Sequence, Tuple

from hpgs_lab import stats
from hpgs_lab.report.tables import METRICS, bench_order, scenes_table
from hpgs_lab.results import RunResult

BASELINE = "random"
SECOND_BASELINE = "farthest"


def comparable(rows: Sequence[RunResult]) -> List[RunResult]:
    """The rows comparisons are made from: first repeats only, no smoke-check scenes, no stress copies."""
    return [r for r in rows if not r.repeat and not r.smoke and "+" not in r.scene]


def comparison_plan(rows: Sequence[RunResult], protocol: str) -> Tuple[List[Tuple[str, str]], List[Tuple[str, str]]]:
    """(primary, other) comparisons of one protocol, fixed before looking at any gain: each selector against
    `random` and against `farthest` (the two baselines a user weighs a selector against; Holm-adjusted together);
    every other pair of selectors is secondary (Holm-adjusted among themselves)."""
    order = bench_order()
    selectors = sorted({r.selector for r in rows if r.protocol == protocol and not r.is_reference},
                       key=lambda s: (order.get(s, 99), s))
    primary = [(s, BASELINE) for s in selectors if s != BASELINE and BASELINE in selectors]
    primary += [(s, SECOND_BASELINE) for s in selectors
                if s not in (BASELINE, SECOND_BASELINE) and SECOND_BASELINE in selectors]
    secondary = [(a, b) for i, a in enumerate(selectors) for b in selectors[i + 1:]
                 if (a, b) not in primary and (b, a) not in primary]
    return primary, secondary


def planned_comparisons(rows: Sequence[RunResult]) -> dict:
    """protocol -> how many primary comparisons Holm adjusts together (`comparison_plan`), for the power section."""
    rows = comparable(rows)
    return {p: len(comparison_plan([r for r in rows if r.protocol == p], p)[0]) for p in {r.protocol for r in rows}}


def protocol_comparisons(group: Sequence[RunResult], protocol: str, metric: str = "psnr") -> List[stats.Comparison]:
    """One protocol's planned comparisons (`comparison_plan`), primary ones Holm-adjusted together: what paired.md
    prints and what the default-selector rule reads."""
    primary, secondary = comparison_plan(group, protocol)
    return stats.compare(group, protocol, primary + secondary, metric=metric, primary=primary, holm_primary=True)


def paired_report(rows: Sequence[RunResult]) -> str:
    """Per protocol: the scenes (training and test views), the paired gain over random per scene, and the
    comparisons with their 95% intervals and verdicts, for PSNR, SSIM and LPIPS."""
    rows = comparable(rows)
    out: List[str] = []
    for protocol in sorted({r.protocol for r in rows}):
        group = [r for r in rows if r.protocol == protocol]
        primary, secondary = comparison_plan(group, protocol)
        if not primary and not secondary:
            continue
        out += [f"#### {protocol} protocol", "", scenes_table(group), ""]
        if not primary:  # run without `random` and `farthest`: every pair Holm-adjusted
            out += ["No `random` or `farthest` runs in this protocol: every comparison is Holm-adjusted.", ""]
        # The code hash covers each selector's own files, so it is counted per selector
        versions = max(len({(r.provenance.settings or {}).get("code") for r in group if r.selector == sel} - {None})
                       for sel in {r.selector for r in group})
        if versions > 1:
            out += [f"A selector's runs here were made by up to {versions} versions of the code (`--accept-code-change`).", ""]
        for sel, _ in [p for p in primary if p[1] == BASELINE]:
            gains = stats.paired_gains(group, sel, BASELINE, protocol, "psnr")
            out += [f"PSNR gain of `{sel}` over `random`, per scene (seeds paired):", "",
                    stats.scene_table(stats.scene_summaries(gains), "psnr"), ""]
        sentences = []
        for metric in METRICS:
            comparisons = protocol_comparisons(group, protocol, metric)
            out += [f"**{metric.upper()}**", "", stats.comparison_table(comparisons), ""]
            if metric == "psnr":
                sentences = [verdict_sentence(c) for c in comparisons if c.n_scenes]
        out += ["In words (PSNR): " + " ".join(sentences), ""]
    return "\n".join(out)


def verdict_sentence(c: stats.Comparison) -> str:
    """One sentence: a ranking only where the comparison's verdict holds, else "indistinguishable"."""
    d = stats.DIGITS[c.metric]
    gain = f"`{c.selector}` - `{c.baseline}` {c.estimate:+.{d}f} dB, 95% CI [{c.lo:+.{d}f}, {c.hi:+.{d}f}], {c.n_scenes} scenes"
    if c.verdict == stats.INDISTINGUISHABLE:
        return f"`{c.selector}` and `{c.baseline}` are indistinguishable here ({gain})."
    better, worse = (c.selector, c.baseline) if c.lo > 0 else (c.baseline, c.selector)
    kind = "primary" if c.primary else "Holm-adjusted"
    return f"`{better}` beats `{worse}` ({gain}, p = {c.p_adjusted:.3g}, {kind})."
