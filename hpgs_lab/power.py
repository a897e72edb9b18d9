"""How often the decision rule (`stats`) would declare a true gain: power, from the variance of the runs at hand.

Model. A selector pair's paired PSNR gain on scene s, seed k is

    g[s, k] = mu + u[s] + e[s, k],    u[s] ~ N(0, tau^2),    e[s, k] ~ N(0, sigma_seed^2)

tau is the between-scene SD of the pair's true gain (some scenes favour a selector more than others) and
sigma_seed the SD of one paired gain around its scene's true gain. sigma_seed already holds the test-set noise
(the gain is a mean over the scene's 7-32 test views); where runs recorded per-view metrics (`RunResult.test_views`)
that part is shown on its own: sigma_view, the SD of per-view paired differences, over sqrt(#test views).

Estimates (`variance_components`): a one-way random-effects ANOVA (method of moments) on each selector pair's
gains, pooled over every pair of selectors run in the protocol, negative variances clamped to 0.

Power (`simulate_power`): draw scenes and seeds from the model with mu = the effect, apply the rule of a primary
comparison (95% hierarchical bootstrap interval above 0 and sign-flip p < 0.05), count the detections. The rule
is `rule`, a vectorised twin of `stats.hierarchical_bootstrap` + `stats.sign_flip_test` that makes the same
draws from the same seed (a test checks it against them); inside the simulation it uses 200 bootstrap draws and,
above 16 scenes, 2000 random sign patterns instead of stats' 10000 and 100000: with 2000 and 20000 instead, the
power of 6 x 3, 10 x 3, 12 x 2 and 20 x 2 designs moved by under 1 point (3000 simulations, 0.9 points of Monte
Carlo error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from hpgs_lab import stats
from hpgs_lab.results import RunResult

EFFECTS_DB = (0.5, 1.0)
TARGET = 0.8
MAX_SCENES = 40
MAX_SEEDS = 10
# The smallest sign-flip p with S scenes is 2 / 2^S: below 6 scenes nothing reaches 0.05.
MIN_SCENES = 6


@dataclass(frozen=True)
class Components:
    """Variance components of the paired gains of one protocol (PSNR, dB), and what they were estimated from."""

    protocol: str
    tau: float
    """Between-scene SD of a selector pair's true gain."""
    sigma_seed: float
    """SD of one paired (scene, seed) gain around its scene's true gain; includes the test-view noise."""
    n_pairs: int
    """Selector pairs pooled."""
    n_scenes: int
    n_gains: int
    """Paired (scene, seed) gains over all pairs."""
    design: Tuple[int, int]
    """(scenes, median seeds per scene) of the pair with the most gains: the design whose power is reported."""
    tau_range: Tuple[float, float] = (math.nan, math.nan)
    """Smallest and largest tau of one pair alone (pairs with two seeds of some scene)."""
    sigma_range: Tuple[float, float] = (math.nan, math.nan)
    sigma_view: Optional[float] = None
    """SD of per-test-view paired differences (None: no pair of runs recorded per-view metrics)."""
    view_noise: Optional[float] = None
    """The test views' part of one paired gain: RMS over paired runs of SD(per-view differences) / sqrt(#views)."""
    n_view_gains: int = 0
    """Paired runs with per-view metrics on both sides."""


def selector_pairs(rows: Sequence[RunResult], protocol: str) -> List[Tuple[str, str]]:
    """Every unordered pair of (non-reference) selectors run under `protocol`, sorted."""
    selectors = sorted({r.selector for r in rows if r.protocol == protocol and not r.is_reference})
    return [(a, b) for i, a in enumerate(selectors) for b in selectors[i + 1:]]


def _view_differences(rows: Sequence[RunResult], a: str, b: str, protocol: str) -> List[np.ndarray]:
    """Per (scene, seed) both ran with per-view metrics: the PSNR differences a - b on the views both have."""
    runs: Dict[str, Dict[Tuple[str, int], RunResult]] = {a: {}, b: {}}
    for r in rows:
        if r.protocol == protocol and r.selector in runs and r.test_views:
            runs[r.selector][r.scene, r.seed] = r
    out = []
    for key in sorted(runs[a].keys() & runs[b].keys()):
        vb = {v.name: v.psnr for v in runs[b][key].test_views}
        d = np.array([v.psnr - vb[v.name] for v in runs[a][key].test_views if v.name in vb], dtype=float)
        if d.size >= 2:
            out.append(d)
    return out


def _anova(per_scene: Sequence[np.ndarray]) -> np.ndarray:
    """[SSW, df_W, SSB, df_B, df_B * n0] of one pair's gains (one array of seeds per scene)."""
    n = np.array([g.size for g in per_scene], dtype=float)
    total = n.sum()
    means = np.array([g.mean() for g in per_scene])
    grand = sum(g.sum() for g in per_scene) / total
    ssw = sum(((g - g.mean()) ** 2).sum() for g in per_scene)
    ssb = (n * (means - grand) ** 2).sum()
    return np.array([ssw, total - n.size, ssb, n.size - 1, total - (n**2).sum() / total])


def _tau_sigma(sums: np.ndarray) -> Optional[Tuple[float, float]]:
    """(tau, sigma) from `_anova` sums (of one pair or pooled); None without the degrees of freedom for both."""
    ssw, dfw, ssb, dfb, dfb_n0 = sums
    if dfw == 0 or dfb == 0:
        return None
    sigma2 = ssw / dfw
    return math.sqrt(max(0.0, (ssb - sigma2 * dfb) / dfb_n0)), math.sqrt(sigma2)


def variance_components(rows: Sequence[RunResult], protocol: str) -> Optional[Components]:
    """tau, sigma_seed (and sigma_view where runs have per-view metrics) of the PSNR gains of `protocol`; None
    when no selector pair has two seeds of one scene and two scenes (nothing to tell the parts apart).

    `rows` are the runs as compared (`report.paired.comparable`: first repeats, no smoke or stress scenes).

    Per pair p (S_p scenes, n_s seeds of scene s, N_p gains): SSW_p = sum (g[s,k] - mean_s)^2 on N_p - S_p
    degrees of freedom, SSB_p = sum_s n_s (mean_s - mean)^2 on S_p - 1, and E[SSB_p] = (S_p - 1)(sigma^2 +
    n0_p tau^2) with n0_p = (N_p - sum n_s^2 / N_p) / (S_p - 1) (the unbalanced one-way ANOVA). Pooled over
    pairs as if they shared tau and sigma: sigma^2 = sum SSW / sum df_W, tau^2 = (sum SSB - sigma^2 sum df_B) /
    sum df_B n0, clamped to >= 0. The pairs of one protocol are not independent (A-B and B-C give A-C), so the
    pooled estimate is the pairs' average variance, not one with as many degrees of freedom as it sums; the
    per-pair estimates' range is kept beside it.
    """
    pooled = np.zeros(5)
    per_pair = []
    n_pairs = n_gains = 0
    scenes: set = set()
    design, most = (0, 0), 0
    view_ss = view_df = view_noise2 = 0.0
    n_view = 0
    for a, b in selector_pairs(rows, protocol):
        gains = stats.paired_gains(rows, a, b, protocol, "psnr")
        per_scene = [np.array(list(g.values()), dtype=float) for g in gains.values() if g]
        total = sum(g.size for g in per_scene)
        if total > most:
            design, most = (len(per_scene), int(np.median([g.size for g in per_scene]))), total
        for d in _view_differences(rows, a, b, protocol):
            view_ss += float(((d - d.mean()) ** 2).sum())
            view_df += d.size - 1
            view_noise2 += float(d.var(ddof=1)) / d.size
            n_view += 1
        if len(per_scene) < 2:
            continue
        sums = _anova(per_scene)
        pooled += sums
        if _tau_sigma(sums) is not None:
            per_pair.append(_tau_sigma(sums))
        n_pairs += 1
        n_gains += total
        scenes |= set(gains)
    estimate = _tau_sigma(pooled)
    if estimate is None:
        return None
    taus, sigmas = zip(*per_pair)
    return Components(
        protocol, *estimate, n_pairs, len(scenes), n_gains, design,
        tau_range=(min(taus), max(taus)), sigma_range=(min(sigmas), max(sigmas)),
        sigma_view=math.sqrt(view_ss / view_df) if view_df else None,
        view_noise=math.sqrt(view_noise2 / n_view) if n_view else None, n_view_gains=n_view)


def rule(gains: np.ndarray, n_boot: int = 10000, n_perm: int = 100000, level: float = 0.95,
         seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """(lo, p) of `stats.compare` for many balanced gain tables at once: gains [n, S, K] (n tables of S scenes x
    K seeds) -> the lower bound of the hierarchical bootstrap interval [n] and the sign-flip p [n].

    The draws are `stats.hierarchical_bootstrap`'s and `stats.sign_flip_test`'s from the same `seed` (shared by
    the n tables, as `compare` shares one seed between comparisons). p is computed only where lo > 0 (NaN
    elsewhere): the rule declares nothing else.
    """
    n, n_scenes, k = gains.shape
    rng = np.random.default_rng(seed)
    scenes = rng.integers(0, n_scenes, size=(n_boot, n_scenes))
    seeds = np.floor(rng.random((n_boot, n_scenes, k)) * k).astype(np.int64)
    # One resample's statistic is a weighted sum of the table: weight = how often a (scene, seed) was drawn.
    cells = (np.arange(n_boot)[:, None, None] * n_scenes + scenes[..., None]) * k + seeds
    weights = np.bincount(cells.ravel(), minlength=n_boot * n_scenes * k).reshape(n_boot, n_scenes * k)
    boot = weights @ gains.reshape(n, n_scenes * k).T / (n_scenes * k)  # [B, n]
    lo = np.quantile(boot, (1 - level) / 2, axis=0)

    p = np.full(n, np.nan)
    todo = np.flatnonzero(lo > 0)
    means = gains[todo].mean(axis=2)  # [m, S] scene means
    observed = np.abs(means.mean(axis=1))
    tol = 1e-12 * np.maximum(1.0, np.abs(means).max(axis=1, initial=0.0))
    if n_scenes <= 16:
        bits = (np.arange(2**n_scenes)[:, None] >> np.arange(n_scenes)) & 1
        signs = 1.0 - 2.0 * bits
        chunk = max(1, 2**22 // 2**n_scenes)  # bounded memory: at most 4M pattern means at once
        for start in range(0, todo.size, chunk):
            part = slice(start, start + chunk)
            flipped = np.abs(signs @ means[part].T) / n_scenes
            p[todo[part]] = np.mean(flipped >= observed[part] - tol[part], axis=0)
    else:
        hits = np.zeros(todo.size)
        rng = np.random.default_rng(seed)
        for start in range(0, n_perm, 10000):
            signs = rng.choice(np.array([-1.0, 1.0]), size=(min(10000, n_perm - start), n_scenes))
            hits += np.sum(np.abs(signs @ means.T) / n_scenes >= observed - tol, axis=0)
        p[todo] = (1 + hits) / (1 + n_perm)
    return lo, p


def simulate_power(effect_db: float, n_scenes: int, n_seeds: int, tau: float, sigma_seed: float,
                   n_sims: int = 400, seed: int = 0, n_boot: int = 200, n_perm: int = 2000,
                   alpha: float = 0.05) -> float:
    """Fraction of `n_sims` simulated benchmarks (n_scenes x n_seeds paired gains drawn from the model with mean
    `effect_db`, every scene with all its seeds) where the rule declares the selector better: interval above 0
    and p < alpha."""
    rng = np.random.default_rng(seed)
    true = effect_db + tau * rng.standard_normal((n_sims, n_scenes, 1))
    gains = true + sigma_seed * rng.standard_normal((n_sims, n_scenes, n_seeds))
    lo, p = rule(gains, n_boot=n_boot, n_perm=n_perm)
    return float(np.mean((lo > 0) & (p < alpha)))


def scenes_needed(effect_db: float, n_seeds: int, tau: float, sigma_seed: float, target: float = TARGET,
                  max_scenes: int = MAX_SCENES, **sim) -> Optional[int]:
    """The fewest scenes (at `n_seeds` each) whose power reaches `target`; None beyond `max_scenes`."""
    for n_scenes in range(MIN_SCENES, max_scenes + 1):
        if simulate_power(effect_db, n_scenes, n_seeds, tau, sigma_seed, **sim) >= target:
            return n_scenes
    return None


def seeds_needed(effect_db: float, n_scenes: int, tau: float, sigma_seed: float, target: float = TARGET,
                 max_seeds: int = MAX_SEEDS, **sim) -> Optional[int]:
    """The fewest seeds per scene (over `n_scenes`) whose power reaches `target`; None beyond `max_seeds` (tau
    caps what seeds can buy: they average out sigma_seed, and the scene means keep their spread tau)."""
    for n_seeds in range(1, max_seeds + 1):
        if simulate_power(effect_db, n_scenes, n_seeds, tau, sigma_seed, **sim) >= target:
            return n_seeds
    return None


def _needed(value: Optional[int], limit: int) -> str:
    return str(value) if value is not None else f"more than {limit}"


def _sd(value: Optional[float]) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def power_section(rows: Sequence[RunResult], effects: Sequence[float] = EFFECTS_DB, target: float = TARGET,
                  n_sims: int = 1000, seed: int = 0, planned: Optional[Dict[str, int]] = None) -> str:
    """Markdown: per protocol, the variance components with what they came from, the power to detect each of
    `effects` (dB) with the current scenes x seeds, and the scenes or seeds that would reach `target`.

    `rows` are the runs as compared (`report.paired.comparable`); "" when no protocol has the runs to tell
    the components apart. `planned`: protocol -> the number m of primary comparisons Holm adjusts together; the
    power is then that of p < 0.05 / m (Bonferroni's, a lower bound on Holm's).
    """
    found = [c for c in (variance_components(rows, p) for p in sorted({r.protocol for r in rows})) if c]
    if not found:
        return ""
    planned = planned or {}
    lines = [
        "SDs of a paired PSNR gain (dB), pooled over every pair of selectors in a protocol (one-way random-effects "
        "ANOVA; in brackets the range over pairs alone). The seed SD includes the test views' noise, shown on its "
        "own where runs recorded per-view metrics.", "",
        "| protocol | selector pairs | scenes | paired gains | between scenes | between seeds | per test view "
        "| test views' part of one gain |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in found:
        view = "n/a (no per-view metrics)" if c.sigma_view is None else f"{c.sigma_view:.2f} ({c.n_view_gains} paired runs)"
        lines.append(f"| {c.protocol} | {c.n_pairs} | {c.n_scenes} | {c.n_gains} | {c.tau:.2f} "
                     f"({c.tau_range[0]:.2f}-{c.tau_range[1]:.2f}) | {c.sigma_seed:.2f} "
                     f"({c.sigma_range[0]:.2f}-{c.sigma_range[1]:.2f}) | {view} | {_sd(c.view_noise)} |")
    lines += [
        "", f"Power of a primary comparison (interval above 0 and p < 0.05 / m, m the protocol's planned comparisons "
        f"that Holm adjusts together) to find a true gain, from {n_sims} "
        "simulated benchmarks with the pooled SDs (and with the largest per-pair SDs), and the scenes or seeds that would "
        f"reach {target:.0%}:", "",
        "| protocol | m | scenes x seeds | true gain | power | largest per-pair SDs | scenes for 80% (same seeds) "
        "| seeds for 80% (same scenes) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in found:
        n_scenes, n_seeds = c.design
        m = max(int(planned.get(c.protocol, 1)), 1)
        sim = dict(n_sims=n_sims, seed=seed, alpha=0.05 / m)
        for effect in effects:
            power = simulate_power(effect, n_scenes, n_seeds, c.tau, c.sigma_seed, **sim)
            worst = simulate_power(effect, n_scenes, n_seeds, c.tau_range[1], c.sigma_range[1], **sim)
            more_scenes = _needed(scenes_needed(effect, n_seeds, c.tau, c.sigma_seed, target, **sim), MAX_SCENES)
            more_seeds = (f"none ({n_scenes} scenes)" if n_scenes < MIN_SCENES else
                          _needed(seeds_needed(effect, n_scenes, c.tau, c.sigma_seed, target, **sim), MAX_SEEDS))
            lines.append(f"| {c.protocol} | {m} | {n_scenes} x {n_seeds} | {effect:+.1f} dB | {power:.0%} | {worst:.0%} | "
                         f"{more_scenes} | {more_seeds} |")
    rough = [c.protocol for c in found if c.n_scenes < MIN_SCENES]
    if rough:
        lines += ["", f"From fewer than {MIN_SCENES} scenes ({', '.join(rough)}) the between-scene SD, and all that "
                  "follows from it, is a rough guess."]
    return "\n".join(lines) + "\n"


__all__ = ["Components", "power_section", "rule", "scenes_needed", "seeds_needed", "selector_pairs",
           "simulate_power", "variance_components"]
