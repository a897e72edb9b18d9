"""The default selector of `ns-train hpgs`, by the rule docs/benchmark.md fixed before the real12 matrix ran: `hpgs`
(the paper's method) stays unless another selector beats it on both rankings, by its runs and by its final-sets
(paired.md's verdict: the 95% interval excludes 0 and the Holm-adjusted p is below 0.05); then the one with the
largest run gain over it. Read from the same comparisons as paired.md, so the page and the rule cannot disagree."""

from __future__ import annotations

from typing import Dict, List, Optional, Sequence

from hpgs_lab import stats
from hpgs_lab.report.paired import comparable, protocol_comparisons
from hpgs_lab.results import RunResult

INCUMBENT = "hpgs"  # the default when the rule was written; the rule keeps naming it so the page reads as fixed


def gains_over(comparisons: Sequence[stats.Comparison], default: str) -> Dict[str, dict]:
    """selector -> its PSNR gain over `default` (estimate, lo, hi) and whether paired.md's verdict ranks it above."""
    out = {}
    for c in comparisons:
        if default not in (c.selector, c.baseline) or not c.n_scenes:
            continue
        other, sign = (c.selector, 1.0) if c.baseline == default else (c.baseline, -1.0)
        lo, hi = sorted((sign * c.lo, sign * c.hi))
        beats = c.verdict != stats.INDISTINGUISHABLE and lo > 0
        out[other] = {"estimate": sign * c.estimate, "lo": lo, "hi": hi, "p": c.p_adjusted, "beats": beats,
                      "scenes": c.n_scenes, "pairs": c.n_pairs}
    return out


def rule_gains(rows: Sequence[RunResult], protocol: str, default: str) -> Dict[str, dict]:
    group = [r for r in comparable(rows) if r.protocol == protocol]
    return gains_over(protocol_comparisons(group, protocol), default)


def default_choice(runs: Dict[str, dict], final_sets: Dict[str, dict], default: str = INCUMBENT) -> str:
    """The selector the rule names: `default` unless others beat it on both rankings, then the largest run gain."""
    both = [s for s in runs if runs[s]["beats"] and final_sets.get(s, {}).get("beats")]
    return max(both, key=lambda s: runs[s]["estimate"]) if both else default


def default_rule_section(rows: Sequence[RunResult], final_rows: Sequence[RunResult], protocol: str = "fisherrf",
                         default: str = INCUMBENT) -> Optional[str]:
    """The rule applied to a results folder's runs and final-sets of one protocol, as markdown (None without both)."""
    runs = rule_gains(rows, protocol, default)
    final_sets = rule_gains(final_rows, protocol, default)
    if not runs or not final_sets:
        return None

    def cell(g: Optional[dict]) -> str:
        if g is None:
            return "–"
        return f"{g['estimate']:+.2f} [{g['lo']:+.2f}, {g['hi']:+.2f}], p {g['p']:.3g}" + (" **beats**" if g["beats"] else "")

    lines: List[str] = [
        f"The rule fixed before the matrix ran (docs/benchmark.md): `{default}` stays the default of `ns-train hpgs` "
        "unless another selector beats it on both rankings (95% interval excluding 0, p < 0.05 after Holm, as above); "
        f"then the one with the largest run gain over it. PSNR gain over `{default}` (dB), protocol `{protocol}`:", "",
        f"| selector | by its runs | by its final-sets | beats `{default}` on both |", "|---|---|---|---|"]
    for s in sorted(runs, key=lambda s: -runs[s]["estimate"]):
        both = runs[s]["beats"] and final_sets.get(s, {}).get("beats", False)
        lines.append(f"| {s} | {cell(runs[s])} | {cell(final_sets.get(s))} | {'yes' if both else 'no'} |")
    choice = default_choice(runs, final_sets, default)
    if choice == default:
        lines += ["", f"On these runs `{default}` stays the default: no selector beats it on both rankings."]
    else:
        lines += ["", f"On these runs the rule names `{choice}`: it beats `{default}` on both rankings, with the "
                      f"largest run gain ({runs[choice]['estimate']:+.2f} dB)."]
    return "\n".join(lines) + "\n"
