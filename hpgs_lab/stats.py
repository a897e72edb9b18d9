"""Is selector A better than selector B? Paired gains, a hierarchical bootstrap and a sign-flip test.

What is compared. Runs are *paired* by (scene, protocol, seed): one scene and one seed share their initial views
and their random stream, so selector A's gain over B on scene s, seed k is `A[s, k] - B[s, k]` (for LPIPS, where
lower is better, `B[s, k] - A[s, k]`: a gain is always positive when A is better, in the metric's own units).
A (scene, seed) that only one of the two selectors ran is left out. Reference rows (`initial`, `all`) are never
compared.

Why this shape. The claim we want is about scenes ("A picks better views than B on scenes like these"), so the
unit of generalisation is the scene, and seeds are nested within scenes: three seeds of one scene are not three
independent scenes. Hence:

* the estimate is the mean over scenes of the per-scene mean gain (every scene weighs the same, whatever its
  number of seeds);
* its interval is a hierarchical percentile bootstrap: resample scenes with replacement, then seeds with
  replacement within each resampled scene;
* its p-value is a two-sided sign-flip permutation test on the per-scene mean gains (H0: the gain's distribution
  over scenes is symmetric about 0), exact over all 2^S sign patterns for S <= 16 scenes, Monte Carlo above.
  The observed pattern and its mirror image always count, so the smallest possible p is 2 / 2^S: 1/32 = 0.03125
  with 6 scenes, 1/16 = 0.0625 with 5. With 5 scenes or fewer nothing can reach p < 0.05; with 6 it does
  exactly when all six scene means have the same (non-zero) sign.

Verdicts. Comparisons named *primary* are fixed in advance and judged on their own p; every other comparison
of one `compare` call is Holm-Bonferroni adjusted together (one family per call, i.e. per protocol and metric).
A verdict "A better than B" / "B better than A" needs both the 95% bootstrap interval to exclude 0 and the
(adjusted where not primary) p < 0.05; otherwise "indistinguishable here", which means "not shown on these
scenes", not "equal". Note that with 6 scenes a Holm-adjusted family of two or more comparisons can never
reach 0.05 (2 x 1/32 = 0.0625): only primary comparisons can be declared with so few scenes.

Per-scene summaries (mean over seeds with a t-interval on n - 1 degrees of freedom) are reported for reading,
not for the verdict. Everything is numpy (plus scipy's t quantile) and seeded: the same rows give the same
numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, Iterable, List, Mapping, Protocol, Sequence, Tuple

import numpy as np

from hpgs_lab.names import REFERENCES


class Run(Protocol):
    """What a comparison reads of a run (`results.RunResult`, or another record with the same fields, e.g.
    `benchmarks/suggest_check.py`'s): `test` has `psnr`, `ssim` and `lpips` attributes."""

    scene: str
    protocol: str
    selector: str
    seed: int
    test: Any

# metric -> True when higher is better
HIGHER_IS_BETTER: Dict[str, bool] = {"psnr": True, "ssim": True, "lpips": False}
DIGITS: Dict[str, int] = {"psnr": 2, "ssim": 3, "lpips": 3}
INDISTINGUISHABLE = "indistinguishable here"
NO_PAIRS = "no paired runs"

Gains = Dict[str, Dict[int, float]]  # scene -> {seed: gain}


def _check_metric(metric: str) -> None:
    if metric not in HIGHER_IS_BETTER:
        raise ValueError(f"unknown metric {metric!r}: expected one of {sorted(HIGHER_IS_BETTER)}")


def _check_level(level: float) -> None:
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")


def _values(rows: Iterable[Run], selector: str, protocol: str, metric: str) -> Dict[Tuple[str, int], float]:
    """(scene, seed) -> the selector's test metric, for one protocol. Two runs of one (scene, seed) are an error."""
    out: Dict[Tuple[str, int], float] = {}
    for r in rows:
        if r.selector != selector or r.protocol != protocol:
            continue
        key = (str(r.scene), int(r.seed))
        if key in out:
            raise ValueError(f"two {selector!r} runs for scene {key[0]!r}, seed {key[1]} under protocol {protocol!r}")
        out[key] = float(getattr(r.test, metric))
    return out


def paired_gains(rows: Iterable[Run], selector: str, baseline: str, protocol: str, metric: str = "psnr") -> Gains:
    """scene -> {seed: gain of `selector` over `baseline`}, on the (scene, seed) pairs both ran under `protocol`.

    gain = selector - baseline for PSNR and SSIM, baseline - selector for LPIPS: positive when `selector` is better.
    """
    _check_metric(metric)
    rows = list(rows)
    a = _values(rows, selector, protocol, metric)
    b = _values(rows, baseline, protocol, metric)
    sign = 1.0 if HIGHER_IS_BETTER[metric] else -1.0
    gains: Gains = {}
    for scene, seed in sorted(a.keys() & b.keys()):
        gains.setdefault(scene, {})[seed] = sign * (a[scene, seed] - b[scene, seed])
    return gains


@dataclass(frozen=True)
class SceneSummary:
    """Mean gain over one scene's seeds and its t-interval (NaN bounds with a single seed)."""

    scene: str
    n_pairs: int
    mean: float
    lo: float
    hi: float


def scene_summaries(gains: Mapping[str, Mapping[int, float]], level: float = 0.95) -> List[SceneSummary]:
    """Per scene (sorted by name): mean gain over seeds, and mean +- t_{(1+level)/2, n-1} * sd / sqrt(n)."""
    _check_level(level)
    out = []
    for scene in sorted(gains):
        g = np.array([gains[scene][k] for k in sorted(gains[scene])], dtype=float)
        if g.size == 0:
            continue
        mean = float(g.mean())
        if g.size < 2:
            lo = hi = math.nan
        else:
            from scipy import stats as scipy_stats  # here: importing scipy.stats takes ~1 s, `hpgs bench --help` none

            half = float(scipy_stats.t.ppf((1 + level) / 2, g.size - 1)) * float(g.std(ddof=1)) / math.sqrt(g.size)
            lo, hi = mean - half, mean + half
        out.append(SceneSummary(scene, int(g.size), mean, lo, hi))
    return out


def scene_means(gains: Mapping[str, Mapping[int, float]]) -> Dict[str, float]:
    """scene -> mean gain over its seeds (scenes without a pair are left out)."""
    return {s: float(np.mean(list(g.values()))) for s, g in sorted(gains.items()) if len(g)}


def _padded(gains: Mapping[str, Mapping[int, float]]) -> Tuple[np.ndarray, np.ndarray]:
    """(S, K_max) gains, zero-padded, and each scene's number of seeds."""
    per_scene = [np.array([g[k] for k in sorted(g)], dtype=float) for _, g in sorted(gains.items()) if len(g)]
    if not per_scene:
        raise ValueError("no paired (scene, seed) gains")
    counts = np.array([v.size for v in per_scene])
    table = np.zeros((len(per_scene), counts.max()))
    for i, v in enumerate(per_scene):
        table[i, : v.size] = v
    return table, counts


def hierarchical_bootstrap(
    gains: Mapping[str, Mapping[int, float]], n_boot: int = 10000, level: float = 0.95, seed: int = 0
) -> Tuple[float, float, float]:
    """(estimate, lo, hi): the mean over scenes of per-scene mean gains, and its percentile bootstrap interval.

    Each resample draws S scenes with replacement, then, within every drawn scene, as many seeds as it has, with
    replacement; its statistic is again the mean over scenes of per-scene means. Vectorised over resamples.
    """
    _check_level(level)
    if n_boot < 1:
        raise ValueError(f"n_boot must be >= 1, got {n_boot}")
    table, counts = _padded(gains)
    n_scenes, k_max = table.shape
    estimate = float(np.mean(table.sum(axis=1) / counts))
    rng = np.random.default_rng(seed)
    scenes = rng.integers(0, n_scenes, size=(n_boot, n_scenes))  # (B, S)
    n = counts[scenes]  # (B, S) seeds in each drawn scene
    # seed draws in [0, n) for every slot; slots beyond a scene's own count are masked out
    seeds = np.floor(rng.random((n_boot, n_scenes, k_max)) * n[..., None]).astype(np.int64)
    used = np.arange(k_max) < n[..., None]  # (B, S, K)
    drawn = table[scenes[..., None], seeds]  # (B, S, K)
    boot = (np.where(used, drawn, 0.0).sum(axis=2) / n).mean(axis=1)  # (B,)
    tail = (1 - level) / 2
    lo, hi = np.quantile(boot, [tail, 1 - tail])
    return estimate, float(lo), float(hi)


def sign_flip_test(
    scene_means: Sequence[float], n_perm: int = 100000, seed: int = 0, max_exact_scenes: int = 16
) -> float:
    """Two-sided sign-flip permutation p-value of "mean over scenes = 0".

    p = fraction of sign patterns whose |mean| >= the observed |mean| (observed pattern included). Exact over all
    2^S patterns when S <= `max_exact_scenes`, so p >= 2 / 2^S (the mirror pattern ties); otherwise `n_perm`
    random patterns from a seeded RNG, p = (1 + hits) / (1 + n_perm). NaN without a scene.
    """
    x = np.asarray(scene_means, dtype=float)
    if x.size == 0:
        return math.nan
    if not np.all(np.isfinite(x)):
        raise ValueError("scene means must be finite")
    observed = abs(float(x.mean()))
    # ties up to rounding: sums of the same numbers in another order may differ in the last bits
    tol = 1e-12 * max(1.0, float(np.abs(x).max()))
    if x.size <= max_exact_scenes:
        bits = (np.arange(2 ** x.size)[:, None] >> np.arange(x.size)) & 1
        signs = 1.0 - 2.0 * bits  # row 0 is the observed pattern
        means = np.abs(signs @ x) / x.size
        return float(np.mean(means >= observed - tol))
    if n_perm < 1:
        raise ValueError(f"n_perm must be >= 1, got {n_perm}")
    rng = np.random.default_rng(seed)
    hits = 0
    for start in range(0, n_perm, 10000):  # bounded memory for many scenes
        m = min(10000, n_perm - start)
        signs = rng.choice(np.array([-1.0, 1.0]), size=(m, x.size))
        hits += int(np.sum(np.abs(signs @ x) / x.size >= observed - tol))
    return (1 + hits) / (1 + n_perm)


def across_scenes(gains: Mapping[str, Mapping[int, float]]) -> Dict[str, float]:
    """The lab scripts' one-line reading of paired gains: mean over scenes of per-scene means, its 95%
    hierarchical-bootstrap interval, the sign-flip p over the scene means, and the scene and pair counts."""
    estimate, lo, hi = hierarchical_bootstrap(gains)
    return {"mean": estimate, "lo": lo, "hi": hi, "p": sign_flip_test(list(scene_means(gains).values())),
            "scenes": len(gains), "pairs": sum(len(v) for v in gains.values())}


def holm(pvalues: Mapping[str, float]) -> Dict[str, float]:
    """Holm-Bonferroni adjusted p-values: sorted ascending, p_(i) * (m - i + 1), running maximum, capped at 1.

    NaN p-values are passed through and not counted in m.
    """
    out = {k: math.nan for k, p in pvalues.items() if not np.isfinite(p)}
    finite = sorted(((float(p), k) for k, p in pvalues.items() if np.isfinite(p)), key=lambda t: t[0])
    m = len(finite)
    running = 0.0
    for i, (p, k) in enumerate(finite):
        running = max(running, min(1.0, (m - i) * p))
        out[k] = running
    return {k: out[k] for k in pvalues}


@dataclass(frozen=True)
class Comparison:
    """Selector vs baseline on one protocol and metric. Gains are positive when `selector` is better.

    `p` is the sign-flip p over scenes; `p_adjusted` is Holm-adjusted over the non-primary comparisons of the same
    `compare` call, and for a primary one equals `p` or (`compare(holm_primary=True)`) is Holm-adjusted over the
    primary ones. `verdict` uses `p_adjusted`.
    """

    selector: str
    baseline: str
    protocol: str
    metric: str
    n_scenes: int
    n_pairs: int
    estimate: float
    lo: float
    hi: float
    p: float
    p_adjusted: float
    primary: bool
    verdict: str
    per_scene: Tuple[SceneSummary, ...] = ()


def verdict(selector: str, baseline: str, lo: float, hi: float, p: float, alpha: float = 0.05) -> str:
    """`"<selector> better than <baseline>"` (or the reverse) when [lo, hi] excludes 0 and p < alpha, else
    "indistinguishable here"."""
    if not (np.isfinite(lo) and np.isfinite(hi) and np.isfinite(p)) or p >= alpha:
        return INDISTINGUISHABLE
    if lo > 0:
        return f"{selector} better than {baseline}"
    if hi < 0:
        return f"{baseline} better than {selector}"
    return INDISTINGUISHABLE


def compare(
    rows: Iterable[Run],
    protocol: str,
    pairs: Sequence[Tuple[str, str]],
    metric: str = "psnr",
    primary: Sequence[Tuple[str, str]] = (),
    n_boot: int = 10000,
    level: float = 0.95,
    alpha: float = 0.05,
    seed: int = 0,
    holm_primary: bool = False,
) -> List[Comparison]:
    """One Comparison per (selector, baseline) in `pairs` (then any `primary` pair not among them), in that order.

    Primary pairs are judged on their unadjusted p, or with `holm_primary` on their p Holm-adjusted over the
    primary pairs; all others are Holm-adjusted together. A pair without a common (scene, seed) gets NaN numbers
    and the verdict "no paired runs" (and is not counted by Holm).
    """
    _check_metric(metric)
    rows = list(rows)
    wanted: List[Tuple[str, str]] = []
    for pair in list(pairs) + list(primary):
        pair = (pair[0], pair[1])
        if pair[0] == pair[1]:
            raise ValueError(f"cannot compare {pair[0]!r} with itself")
        if set(pair) & set(REFERENCES):
            raise ValueError(f"reference rows {REFERENCES} are not compared: {pair}")
        if pair not in wanted:
            wanted.append(pair)
    primary_set = {(a, b) for a, b in primary}

    raw = []
    for a, b in wanted:
        gains = paired_gains(rows, a, b, protocol, metric)
        if not gains:
            raw.append((a, b, 0, 0, math.nan, math.nan, math.nan, math.nan, ()))
            continue
        est, lo, hi = hierarchical_bootstrap(gains, n_boot=n_boot, level=level, seed=seed)
        p = sign_flip_test(list(scene_means(gains).values()), seed=seed)
        per_scene = tuple(scene_summaries(gains, level))
        raw.append((a, b, len(gains), sum(len(g) for g in gains.values()), est, lo, hi, p, per_scene))

    adjusted = holm({f"{r[0]}\0{r[1]}": r[7] for r in raw if (r[0], r[1]) not in primary_set})
    if holm_primary:
        adjusted.update(holm({f"{r[0]}\0{r[1]}": r[7] for r in raw if (r[0], r[1]) in primary_set}))
    out = []
    for a, b, n_scenes, n_pairs, est, lo, hi, p, per_scene in raw:
        is_primary = (a, b) in primary_set
        p_adj = p if is_primary and not holm_primary else adjusted[f"{a}\0{b}"]
        v = NO_PAIRS if n_scenes == 0 else verdict(a, b, lo, hi, p_adj, alpha)
        out.append(
            Comparison(a, b, protocol, metric, n_scenes, n_pairs, est, lo, hi, p, p_adj, is_primary, v, per_scene)
        )
    return out


def _gain(x: float, digits: int) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:+.{digits}f}"


def _interval(lo: float, hi: float, digits: int) -> str:
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return "n/a"
    return f"[{lo:+.{digits}f}, {hi:+.{digits}f}]"


def _p(c: Comparison) -> str:
    if not np.isfinite(c.p):
        return "n/a"
    if c.primary:
        if c.p_adjusted == c.p:
            return f"{c.p:.3g} (primary)"
        return f"{c.p_adjusted:.3g} (primary, Holm; raw {c.p:.3g})"
    return f"{c.p_adjusted:.3g} (Holm; raw {c.p:.3g})"


SIGN_NOTE = "Gain = A - B (LPIPS: B - A), so a positive gain means A is better."


def comparison_table(comparisons: Sequence[Comparison]) -> str:
    """Markdown table, one line per comparison ("A vs B"), then a line stating the sign convention."""
    lines = [
        "| comparison | metric | scenes | pairs | mean gain | 95% CI | p | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in comparisons:
        d = DIGITS[c.metric]
        lines.append(
            f"| {c.selector} vs {c.baseline} | {c.metric.upper()} | {c.n_scenes} | {c.n_pairs} | "
            f"{_gain(c.estimate, d)} | {_interval(c.lo, c.hi, d)} | {_p(c)} | {c.verdict} |"
        )
    return "\n".join(lines + ["", SIGN_NOTE])


def scene_table(summaries: Sequence[SceneSummary], metric: str = "psnr") -> str:
    """Markdown table of per-scene mean gains over seeds, with t-intervals ("n/a" with a single seed)."""
    _check_metric(metric)
    d = DIGITS[metric]
    lines = ["| scene | pairs | mean gain | 95% CI |", "|---|---|---|---|"]
    for s in summaries:
        ci = _interval(s.lo, s.hi, d) if s.n_pairs > 1 else "n/a (1 seed)"
        lines.append(f"| {s.scene} | {s.n_pairs} | {_gain(s.mean, d)} | {ci} |")
    return "\n".join(lines)


__all__ = [
    "Comparison",
    "HIGHER_IS_BETTER",
    "Run",
    "SceneSummary",
    "compare",
    "comparison_table",
    "hierarchical_bootstrap",
    "holm",
    "paired_gains",
    "scene_means",
    "scene_summaries",
    "scene_table",
    "sign_flip_test",
    "verdict",
]
