"""`hpgs_lab.stats`: paired gains, hierarchical bootstrap, sign-flip test, Holm, verdicts, tables.

Known cases with numbers worked out by hand: identical runs, a constant shift, a gain on one scene only.
"""

from __future__ import annotations

import math
from typing import Dict, List, Tuple

import numpy as np
import pytest
from helpers import make_result

from hpgs_lab.results import RunResult
from hpgs_lab.stats import (
    compare,
    comparison_table,
    hierarchical_bootstrap,
    holm,
    paired_gains,
    scene_means,
    scene_summaries,
    scene_table,
    sign_flip_test,
)

SCENES = [f"scene{i}" for i in range(6)]
SEEDS = [0, 1, 2]


def rows_for(selector: str, psnr: Dict[Tuple[str, int], float], protocol: str = "hpgs", lpips=None) -> List[RunResult]:
    """One run per (scene, seed); SSIM follows PSNR, LPIPS given or derived from it."""
    out = []
    for (scene, seed), value in psnr.items():
        lp = lpips[scene, seed] if lpips is not None else 0.5 - value / 100
        out.append(make_result(scene, protocol, selector, seed, value, value / 40, lp))
    return out


def noisy_base(seed: int = 1, scenes=SCENES, seeds=SEEDS) -> Dict[Tuple[str, int], float]:
    rng = np.random.default_rng(seed)
    return {(s, k): float(20 + 5 * rng.random() + rng.normal()) for s in scenes for k in seeds}


# ---------------------------------------------------------------------------------------------------------------
# Known cases


def test_identical_runs_give_zero_with_a_zero_interval_and_p_one():
    base = noisy_base()
    rows = rows_for("random", base) + rows_for("hpgs", base)
    gains = paired_gains(rows, "hpgs", "random", "hpgs")
    assert hierarchical_bootstrap(gains) == (0.0, 0.0, 0.0)
    assert sign_flip_test(list(scene_means(gains).values())) == 1.0
    [c] = compare(rows, "hpgs", [("hpgs", "random")], primary=[("hpgs", "random")])
    assert (c.n_scenes, c.n_pairs, c.estimate, c.lo, c.hi, c.p) == (6, 18, 0.0, 0.0, 0.0, 1.0)
    assert c.verdict == "indistinguishable here"


@pytest.mark.parametrize("n_scenes", [3, 5, 6, 8])
def test_a_constant_shift_is_recovered_exactly(n_scenes):
    scenes = SCENES[:1] + [f"s{i}" for i in range(n_scenes - 1)]
    base = noisy_base(seed=n_scenes, scenes=scenes)
    rows = rows_for("random", base) + rows_for("hpgs", {k: v + 0.7 for k, v in base.items()})
    [c] = compare(rows, "hpgs", [("hpgs", "random")], primary=[("hpgs", "random")])
    assert c.estimate == pytest.approx(0.7, abs=1e-9)
    assert c.lo == pytest.approx(0.7, abs=1e-9) and c.hi == pytest.approx(0.7, abs=1e-9)
    assert c.p == pytest.approx(2 / 2 ** n_scenes)
    # 5 scenes: p = 1/16 > 0.05, nothing can be declared; 6: p = 1/32
    assert c.verdict == ("hpgs better than random" if n_scenes >= 6 else "indistinguishable here")


def test_the_reverse_comparison_names_the_better_one_second():
    base = noisy_base()
    rows = rows_for("random", base) + rows_for("hpgs", {k: v + 0.7 for k, v in base.items()})
    [c] = compare(rows, "hpgs", [("random", "hpgs")], primary=[("random", "hpgs")])
    assert c.estimate == pytest.approx(-0.7, abs=1e-9)
    assert c.verdict == "hpgs better than random"


@pytest.mark.parametrize("others", [0.0, -0.1])
def test_a_gain_on_one_scene_only_is_not_significant(others):
    base = noisy_base()
    shifted = {(s, k): v + (3.0 if s == SCENES[0] else others) for (s, k), v in base.items()}
    rows = rows_for("random", base) + rows_for("hpgs", shifted)
    [c] = compare(rows, "hpgs", [("hpgs", "random")], primary=[("hpgs", "random")])
    assert c.estimate == pytest.approx((3.0 + 5 * others) / 6, abs=1e-9)
    assert c.lo <= 1e-9 < c.hi  # scene0 is left out of a third of the resamples: (5/6)^6
    # every pattern's |sum| is |3 + 0.1 j| (j = -5..5) or 3: never below the observed 2.5 (or 3) -> p = 1
    assert c.p == 1.0
    assert c.verdict == "indistinguishable here"


def test_one_large_scene_against_five_small_opposite_ones():
    means = [3.0, -0.5, -0.5, -0.5, -0.5, -0.5]  # observed mean 0.5/6
    # |sum| >= 0.5 for every pattern: 3 +- (five 0.5s) sums to 3 + 0.5*j, j odd in [-5, 5] -> |.| >= 0.5
    assert sign_flip_test(means) == 1.0


# ---------------------------------------------------------------------------------------------------------------
# Pieces


def test_pairing_leaves_out_unmatched_runs_and_other_protocols():
    a = {("s0", 0): 21.0, ("s0", 1): 22.0, ("s0", 2): 30.0, ("s1", 0): 25.0}
    b = {("s0", 0): 20.0, ("s0", 1): 20.5, ("s1", 0): 26.0, ("s2", 0): 10.0}
    rows = rows_for("hpgs", a) + rows_for("random", b) + rows_for("hpgs", {("s2", 0): 99.0}, protocol="fisherrf")
    rows += rows_for("initial", b)
    gains = paired_gains(rows, "hpgs", "random", "hpgs")
    assert gains == {"s0": {0: 1.0, 1: 1.5}, "s1": {0: -1.0}}
    [c] = compare(rows, "hpgs", [("hpgs", "random")])
    assert (c.n_scenes, c.n_pairs) == (2, 3)
    assert c.estimate == pytest.approx((1.25 - 1.0) / 2)


def test_a_pair_without_common_runs_reports_no_pairs():
    rows = rows_for("hpgs", {("s0", 0): 21.0}) + rows_for("random", {("s1", 0): 20.0})
    [c] = compare(rows, "hpgs", [("hpgs", "random")])
    assert (c.n_scenes, c.n_pairs, c.verdict) == (0, 0, "no paired runs")
    assert math.isnan(c.estimate) and math.isnan(c.p)


def test_duplicate_runs_and_reference_rows_are_refused():
    rows = rows_for("hpgs", {("s0", 0): 21.0}) * 2 + rows_for("random", {("s0", 0): 20.0})
    with pytest.raises(ValueError, match="two 'hpgs' runs"):
        paired_gains(rows, "hpgs", "random", "hpgs")
    with pytest.raises(ValueError, match="reference"):
        compare(rows, "hpgs", [("hpgs", "all")])
    with pytest.raises(ValueError, match="unknown metric"):
        paired_gains(rows, "hpgs", "random", "hpgs", metric="mse")


def test_lpips_gain_is_positive_when_lower():
    psnr = {("s0", 0): 20.0, ("s0", 1): 20.0}
    rows = rows_for("hpgs", psnr, lpips={("s0", 0): 0.20, ("s0", 1): 0.25})
    rows += rows_for("random", psnr, lpips={("s0", 0): 0.30, ("s0", 1): 0.30})
    gains = paired_gains(rows, "hpgs", "random", "hpgs", metric="lpips")
    assert gains["s0"][0] == pytest.approx(0.10) and gains["s0"][1] == pytest.approx(0.05)
    assert paired_gains(rows, "random", "hpgs", "hpgs", metric="lpips")["s0"][0] == pytest.approx(-0.10)


def test_lpips_verdict_over_six_scenes():
    base = noisy_base()
    lp_b = {k: 0.3 + 0.01 * (v - 20) for k, v in base.items()}
    lp_a = {k: v - 0.02 for k, v in lp_b.items()}
    rows = rows_for("random", base, lpips=lp_b) + rows_for("hpgs", base, lpips=lp_a)
    [c] = compare(rows, "hpgs", [("hpgs", "random")], metric="lpips", primary=[("hpgs", "random")])
    assert c.estimate == pytest.approx(0.02, abs=1e-9)
    assert c.verdict == "hpgs better than random"


def test_holm_textbook_example():
    adjusted = holm({"a": 0.01, "b": 0.04, "c": 0.03, "d": 0.005})
    assert list(adjusted) == ["a", "b", "c", "d"]
    assert [adjusted[k] for k in "abcd"] == pytest.approx([0.03, 0.06, 0.06, 0.02])


def test_holm_is_capped_at_one_and_passes_nan_through():
    adjusted = holm({"a": 0.4, "b": 0.6, "c": float("nan")})
    assert adjusted["a"] == pytest.approx(0.8) and adjusted["b"] == pytest.approx(0.8)  # monotone: max(0.8, 0.6)
    assert math.isnan(adjusted["c"])
    assert holm({"a": 0.9, "b": 0.95})["a"] == 1.0
    assert holm({}) == {}


def test_sign_flip_exact_on_hand_computed_examples():
    # sums over the 8 patterns of (1, 2, 3): +-6, +-4, +-2, 0, 0; |.| >= 6: 2 of 8
    assert sign_flip_test([1.0, 2.0, 3.0]) == 0.25
    # (1, -2, 3): observed sum 2; |sums| = 2, 4, 6, 0, 0, 6, 4, 2 -> 6 of 8
    assert sign_flip_test([1.0, -2.0, 3.0]) == 0.75
    assert sign_flip_test([5.0]) == 1.0  # one scene: its mirror always ties
    assert sign_flip_test([0.0, 0.0]) == 1.0
    assert math.isnan(sign_flip_test([]))


def test_sign_flip_monte_carlo_matches_exact_and_is_seeded():
    rng = np.random.default_rng(3)
    x = rng.normal(0.3, 1.0, size=12)
    exact = sign_flip_test(x)
    mc = sign_flip_test(x, n_perm=40000, seed=1, max_exact_scenes=0)
    assert mc == pytest.approx(exact, abs=0.01)
    assert mc == sign_flip_test(x, n_perm=40000, seed=1, max_exact_scenes=0)
    # 20 scenes all positive: exact p would be 2^-19, Monte Carlo floors it at 1 / (n_perm + 1)
    assert sign_flip_test(np.ones(20), n_perm=9999) == pytest.approx(1e-4)


def test_bootstrap_is_reproducible_and_covers_the_estimate():
    rng = np.random.default_rng(0)
    gains = {s: {k: float(rng.normal(0.4, 0.5)) for k in SEEDS} for s in SCENES}
    est, lo, hi = hierarchical_bootstrap(gains, seed=7)
    assert (est, lo, hi) == hierarchical_bootstrap(gains, seed=7)
    assert hierarchical_bootstrap(gains, seed=8) != (est, lo, hi)
    assert est == pytest.approx(np.mean([np.mean(list(g.values())) for g in gains.values()]))
    assert lo < est < hi
    # wider at 99% than at 95%
    _, lo99, hi99 = hierarchical_bootstrap(gains, level=0.99, seed=7)
    assert lo99 < lo and hi < hi99


def test_bootstrap_weighs_scenes_equally_and_handles_uneven_seeds():
    gains = {"a": {0: 1.0, 1: 1.0, 2: 1.0, 3: 1.0}, "b": {0: 3.0}}
    est, lo, hi = hierarchical_bootstrap(gains, n_boot=4000)
    assert est == 2.0  # mean of scene means, not of the 5 pairs (1.4)
    # only scenes vary: resamples are (a, a) -> 1, (a, b) -> 2, (b, b) -> 3
    assert lo == 1.0 and hi == 3.0


def test_bootstrap_resamples_seeds_within_a_scene():
    gains = {"a": {0: 0.0, 1: 1.0}}  # one scene: only seeds vary, means in {0, 0.5, 1}
    boot_est, lo, hi = hierarchical_bootstrap(gains, n_boot=4000)
    assert boot_est == 0.5 and lo == 0.0 and hi == 1.0


def test_scene_summaries_t_interval():
    [s1, s2] = scene_summaries({"a": {0: 1.0, 1: 2.0, 2: 3.0}, "b": {4: 0.5}})
    # mean 2, sd 1, t_{0.975, 2} = 4.302652729911275
    half = 4.302652729911275 / math.sqrt(3)
    assert (s1.scene, s1.n_pairs, s1.mean) == ("a", 3, 2.0)
    assert s1.lo == pytest.approx(2 - half) and s1.hi == pytest.approx(2 + half)
    assert (s2.scene, s2.n_pairs, s2.mean) == ("b", 1, 0.5)
    assert math.isnan(s2.lo) and math.isnan(s2.hi)


# ---------------------------------------------------------------------------------------------------------------
# compare: primary vs Holm, tables


def test_primary_is_unadjusted_and_the_others_are_holm_adjusted_together():
    base = noisy_base()
    rows = rows_for("random", base)
    rows += rows_for("hpgs", {k: v + 0.7 for k, v in base.items()})
    rows += rows_for("fisher", {k: v + 0.5 for k, v in base.items()})
    rows += rows_for("farthest", {k: v + 0.3 for k, v in base.items()})
    pairs = [("hpgs", "random"), ("fisher", "random"), ("farthest", "random")]
    out = compare(rows, "hpgs", pairs, primary=[("hpgs", "random")])
    assert [(c.selector, c.primary) for c in out] == [("hpgs", True), ("fisher", False), ("farthest", False)]
    assert all(c.p == pytest.approx(1 / 32) for c in out)
    assert out[0].p_adjusted == pytest.approx(1 / 32) and out[0].verdict == "hpgs better than random"
    # two non-primary: Holm gives 2/32 = 0.0625 > 0.05, though their intervals exclude 0
    for c in out[1:]:
        assert c.p_adjusted == pytest.approx(1 / 16) and c.lo > 0
        assert c.verdict == "indistinguishable here"


def test_with_holm_primary_the_primary_pairs_are_holm_adjusted_among_themselves():
    base = noisy_base()
    rows = rows_for("random", base)
    rows += rows_for("hpgs", {k: v + 0.7 for k, v in base.items()})
    rows += rows_for("fisher", {k: v + 0.5 for k, v in base.items()})
    rows += rows_for("farthest", {k: v + 0.3 for k, v in base.items()})
    primary = [("hpgs", "random"), ("fisher", "random")]
    out = compare(rows, "hpgs", [("farthest", "random")], primary=primary, holm_primary=True)
    by = {c.selector: c for c in out}
    # two primaries, each raw 1/32: Holm over the two gives 2/32 = 0.0625 > 0.05 though their intervals exclude 0
    for sel in ("hpgs", "fisher"):
        assert by[sel].primary and by[sel].p_adjusted == pytest.approx(1 / 16) and by[sel].lo > 0
        assert by[sel].verdict == "indistinguishable here"
    # the one secondary is adjusted on its own (m = 1): its raw p
    assert by["farthest"].p_adjusted == pytest.approx(1 / 32) and by["farthest"].verdict == "farthest better than random"
    assert "0.0625 (primary, Holm; raw 0.0312)" in comparison_table(out)


def test_a_primary_pair_not_listed_in_pairs_is_still_compared():
    base = noisy_base()
    rows = rows_for("random", base) + rows_for("hpgs", {k: v + 0.7 for k, v in base.items()})
    out = compare(rows, "hpgs", [], primary=[("hpgs", "random")])
    assert [(c.selector, c.baseline, c.primary) for c in out] == [("hpgs", "random", True)]


def test_tables():
    base = noisy_base()
    rows = rows_for("random", base) + rows_for("hpgs", {k: v + 0.7 for k, v in base.items()})
    [c] = compare(rows, "hpgs", [("hpgs", "random")], primary=[("hpgs", "random")])
    table = comparison_table([c])
    lines = table.splitlines()
    assert lines[0] == "| comparison | metric | scenes | pairs | mean gain | 95% CI | p | verdict |"
    assert lines[2] == "| hpgs vs random | PSNR | 6 | 18 | +0.70 | [+0.70, +0.70] | 0.0312 (primary) | hpgs better than random |"
    assert "positive gain means A is better" in table

    rows_ssim = rows_for("random", base) + rows_for("hpgs", {k: v + 0.8 for k, v in base.items()})  # SSIM +0.02
    [s] = compare(rows_ssim, "hpgs", [("hpgs", "random")], metric="ssim")  # not primary: Holm over one = raw
    assert s.estimate == pytest.approx(0.02) and s.p_adjusted == pytest.approx(1 / 32)
    expected = "| SSIM | 6 | 18 | +0.020 | [+0.020, +0.020] | 0.0312 (Holm; raw 0.0312) | hpgs better than random |"
    assert expected in comparison_table([s])

    per_scene = scene_table(c.per_scene, "psnr").splitlines()
    assert per_scene[0] == "| scene | pairs | mean gain | 95% CI |"
    assert per_scene[2] == "| scene0 | 3 | +0.70 | [+0.70, +0.70] |"
    assert len(per_scene) == 2 + 6
    one_seed = scene_table(scene_summaries({"x": {0: -0.0123}}), "lpips").splitlines()[2]
    assert one_seed == "| x | 1 | -0.012 | n/a (1 seed) |"
