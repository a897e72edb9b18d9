"""`bench.power`: the variance components of paired gains, and the power of the decision rule, on data whose
answer is known (hand-computed ANOVA, the six-scene rule, a normal approximation, a large simulated matrix)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import make_result, write_rows
from scipy.stats import norm

from hpgs_lab import stats
from hpgs_lab.power import power_section, rule, scenes_needed, seeds_needed, simulate_power, variance_components
from hpgs_lab.report import write_report
from hpgs_lab.results import ViewMetrics

# --- the rule: the vectorised twin against stats.py ---------------------------------------------------------


@pytest.mark.parametrize("n_scenes, n_seeds", [(6, 3), (7, 2), (12, 2), (18, 2)])
def test_the_vectorised_rule_is_stats_rule(n_scenes, n_seeds):
    rng = np.random.default_rng(n_scenes)
    tables = 0.4 + 0.3 * rng.standard_normal((40, n_scenes, 1)) + 0.8 * rng.standard_normal((40, n_scenes, n_seeds))
    lo, p = rule(tables, n_boot=300, n_perm=3000)
    declared = 0
    for table, lo_i, p_i in zip(tables, lo, p):
        gains = {f"s{i:02d}": dict(enumerate(row)) for i, row in enumerate(table)}  # stats sorts by name
        _, want_lo, want_hi = stats.hierarchical_bootstrap(gains, n_boot=300)
        assert lo_i == pytest.approx(want_lo, abs=1e-12)
        if lo_i > 0:  # p is only computed where the interval can declare a gain
            want_p = stats.sign_flip_test(list(stats.scene_means(gains).values()), n_perm=3000)
            assert p_i == want_p
            declared += stats.verdict("a", "b", want_lo, want_hi, want_p) == "a better than b"
        else:
            assert math.isnan(p_i)
    assert 0 < int(np.sum(lo > 0)) < 40 and declared == int(np.sum((lo > 0) & (p < 0.05)))


# --- power on cases with a known answer ---------------------------------------------------------------------


def test_with_six_scenes_power_is_the_chance_that_all_six_scene_means_are_positive():
    # 6 scenes: p = 2/64 when all six scene means share a sign, >= 4/64 otherwise; all positive puts every
    # bootstrap mean above 0. So power = Phi(effect / sd(scene mean))^6 exactly, sd^2 = tau^2 + sigma^2 / K.
    effect, tau, sigma, k = 0.5, 0.46, 0.77, 3
    exact = norm.cdf(effect / math.sqrt(tau**2 + sigma**2 / k)) ** 6  # 0.226: the "6 scenes x 3 seeds"
    power = simulate_power(effect, 6, k, tau, sigma, n_sims=4000)
    assert power == pytest.approx(exact, abs=0.025)  # 3.8 Monte Carlo SEs (sqrt(0.23 * 0.77 / 4000) = 0.0066)
    assert simulate_power(0.0, 6, 3, 0.0, 1.0, n_sims=4000) == pytest.approx(1 / 64, abs=0.008)  # 4 SEs


def test_five_scenes_never_and_a_huge_gain_always():
    assert simulate_power(10.0, 5, 3, 0.1, 0.1) == 0.0  # smallest p with 5 scenes: 2/32 = 0.0625
    assert simulate_power(10.0, 6, 3, 0.1, 0.1) == 1.0
    assert simulate_power(5.0, 12, 2, 0.46, 0.77) == 1.0  # a scene mean below 0 is a 7-SD event


def test_without_a_gain_the_rule_declares_one_at_most_half_alpha_of_the_time():
    # two-sided p < 0.05: at most 2.5% in the positive direction, less with the interval as well
    assert simulate_power(0.0, 12, 2, 0.46, 0.77, n_sims=2000) <= 0.025 + 3 * math.sqrt(0.025 * 0.975 / 2000)


@pytest.mark.parametrize("n_scenes, n_seeds, effect, tau", [(40, 1, 0.3, 0.0), (30, 2, 0.3, 0.3)])
def test_with_many_scenes_power_follows_the_normal_approximation_of_the_sign_flip_test(n_scenes, n_seeds, effect, tau):
    # The sign-flip null of the mean over S scenes is ~N(0, sum x^2 / S^2), and E[x^2] = effect^2 + v with
    # v = tau^2 + sigma^2 / K; the mean is ~N(effect, v / S). Detected ~ when mean > 1.96 sqrt((effect^2 + v) / S).
    # Tolerance: 0.0075 Monte Carlo SE at 4000 runs, plus the approximation's own error (a random denominator).
    sigma = 1.0 if n_seeds == 1 else 0.8
    v = tau**2 + sigma**2 / n_seeds
    approx = norm.cdf((effect - 1.96 * math.sqrt((effect**2 + v) / n_scenes)) / math.sqrt(v / n_scenes))
    assert simulate_power(effect, n_scenes, n_seeds, tau, sigma, n_sims=4000) == pytest.approx(approx, abs=0.035)


def test_scenes_and_seeds_needed():
    # 6 scenes, tau 0: power = Phi(0.95 sqrt(K))^6 = 0.735 with 3 seeds, 0.839 with 4 (see the six-scene test)
    assert seeds_needed(0.95, 6, 0.0, 1.0, n_sims=2000) == 4
    assert scenes_needed(0.95, 4, 0.0, 1.0, n_sims=2000) == 6
    # tau caps what seeds buy: scene means stay ~N(0.5, 2^2) however many seeds
    assert seeds_needed(0.5, 12, 2.0, 0.5, n_sims=400) is None
    assert scenes_needed(0.5, 1, 0.0, 20.0, max_scenes=12, n_sims=400) is None


# --- variance components ------------------------------------------------------------------------------------


def gain_rows(gains: dict, protocol: str = "fisherrf") -> list:
    """`random` at 20 dB and `a` at 20 + gain, for {scene: [gain per seed]}."""
    return [make_result(scene, protocol, sel, seed, 20.0 + (g if sel == "a" else 0.0))
            for scene, per_seed in gains.items() for seed, g in enumerate(per_seed) for sel in ("random", "a")]


def test_the_anova_by_hand():
    # scene means 1, 5, 3 over 2, 1, 2 seeds; grand mean 13/5. SSW = 4 on 2 df: sigma^2 = 2. SSB = 2 * 1.6^2 +
    # 2.4^2 + 2 * 0.4^2 = 11.2 on 2 df, n0 = (5 - 9/5) / 2 = 1.6: tau^2 = (11.2 - 2 * 2) / (2 * 1.6) = 2.25.
    c = variance_components(gain_rows({"x": [0, 2], "y": [5], "z": [2, 4]}), "fisherrf")
    assert (c.tau, c.sigma_seed) == (pytest.approx(1.5), pytest.approx(math.sqrt(2)))
    assert (c.n_pairs, c.n_scenes, c.n_gains, c.design) == (1, 3, 5, (3, 2))
    assert c.sigma_view is None and c.view_noise is None
    # identical scene means: SSB = 0 < its expectation, tau^2 < 0 clamped
    c = variance_components(gain_rows({f"s{i}": [1, -1] for i in range(4)}), "fisherrf")
    assert (c.tau, c.sigma_seed) == (0.0, pytest.approx(math.sqrt(2)))
    # one seed per scene: nothing tells the parts apart
    assert variance_components(gain_rows({"x": [1], "y": [2]}), "fisherrf") is None


def simulated_matrix(n_scenes=200, n_seeds=3, n_views=12, t=0.3, s=0.4, w=1.9, seed=0) -> list:
    """Runs of three selectors whose test views' PSNR is base[scene, seed] + view[scene, v] (shared by every run)
    + the selector's own scene effect (SD t) + run noise (SD s) + view noise (SD w)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_scenes):
        view = 3.0 * rng.standard_normal(n_views)
        own = {sel: t * rng.standard_normal() for sel in ("random", "a", "b")}
        for k in range(n_seeds):
            base = 20.0 + 2.0 * rng.standard_normal()
            for sel, mu in (("random", 0.0), ("a", 0.5), ("b", 0.2)):
                psnr = base + mu + own[sel] + s * rng.standard_normal() + view + w * rng.standard_normal(n_views)
                views = [ViewMetrics(f"v{v}.png", float(x), 0.5, 0.3) for v, x in enumerate(psnr)]
                out.append(make_result(f"s{i}", "fisherrf", sel, k, float(psnr.mean()), test_views=views))
    return out


def test_the_components_of_a_large_simulated_matrix_are_recovered():
    c = variance_components(simulated_matrix(), "fisherrf")
    # a pair's gain: tau^2 = 2 t^2, sigma_seed^2 = 2 s^2 + 2 w^2 / 12, per-view differences 2 w^2
    tau, sigma = math.sqrt(2 * 0.3**2), math.sqrt(2 * 0.4**2 + 2 * 1.9**2 / 12)
    assert (c.n_pairs, c.n_scenes, c.n_gains, c.design, c.n_view_gains) == (3, 200, 1800, (200, 3), 1800)
    assert c.sigma_seed == pytest.approx(sigma, rel=0.08)  # 2.3 SEs of one pair alone (chi^2 on 400 df: 3.5%)
    assert c.tau == pytest.approx(tau, abs=0.15)  # SE of tau^2 ~ sqrt(2/199) * (tau^2 + sigma^2/3) = 0.05
    assert c.sigma_view == pytest.approx(math.sqrt(2) * 1.9, rel=0.03)  # 6600 df per pair
    assert c.view_noise == pytest.approx(math.sqrt(2) * 1.9 / math.sqrt(12), rel=0.03)


# --- the report ---------------------------------------------------------------------------------------------


def test_the_power_section_and_the_results_page(tmp_path):
    rows = gain_rows({"x": [0, 2], "y": [5], "z": [2, 4]})
    text = power_section(rows, n_sims=200)
    assert "| fisherrf | 1 | 3 | 5 | 1.50 (1.50-1.50) | 1.41 (1.41-1.41) | n/a (no per-view metrics) | n/a |" in text
    assert "| fisherrf | 1 | 3 x 2 | +0.5 dB | 0% | 0% |" in text and "| none (3 scenes) |" in text  # 3 scenes: never
    assert power_section(gain_rows({"x": [1], "y": [2]})) == ""

    out = tmp_path / "suite"
    write_rows(out, simulated_matrix(n_scenes=6, n_seeds=2, n_views=4, t=0.1, s=0.2, w=0.5))
    page = tmp_path / "results.md"
    written = write_report(out, results_page=page)
    assert out / "power.md" in written
    text = page.read_text()
    assert "## Power" in text and (out / "power.md").read_text() in text
    assert "| fisherrf | 3 | 6 | 36 |" in text and "(36 paired runs)" in text  # every paired run had its views
    # two planned comparisons (a and b against random): p < 0.025, which 6 scenes (smallest p 2/64) never reach
    assert "| fisherrf | 2 | 6 x 2 | +1.0 dB | 0% | 0% |" in text
