"""The default-selector rule of docs/benchmark.md, read from paired.md's comparisons: `hpgs` stays unless another
selector beats it on both rankings; then the largest run gain."""

from __future__ import annotations

from hpgs_lab import stats
from hpgs_lab.report.default_rule import default_choice, gains_over


def comparison(selector, baseline, estimate, lo, hi, p):
    verdict = stats.verdict(selector, baseline, lo, hi, p)
    return stats.Comparison(selector, baseline, "fisherrf", "psnr", 12, 24, estimate, lo, hi, p, p, False, verdict)


def test_a_gain_is_read_from_either_side_of_the_comparison():
    got = gains_over([comparison("hpgs", "farthest", -0.48, -0.88, -0.07, 0.035),
                      comparison("fisher", "hpgs", 0.50, 0.03, 0.99, 0.043),
                      comparison("hpgs", "random", 0.41, -0.03, 0.83, 0.096),
                      comparison("fisher", "farthest", 0.03, -0.39, 0.41, 0.88)], "hpgs")
    assert set(got) == {"farthest", "fisher", "random"}  # fisher vs farthest does not involve hpgs
    assert (got["farthest"]["estimate"], got["farthest"]["lo"], got["farthest"]["hi"]) == (0.48, 0.07, 0.88)
    assert got["farthest"]["beats"] and got["fisher"]["beats"]
    assert not got["random"]["beats"] and got["random"]["estimate"] == -0.41


def test_hpgs_stays_unless_beaten_on_both_rankings_then_the_largest_run_gain_wins():
    runs = {"farthest": {"estimate": 0.48, "beats": True}, "fisher": {"estimate": 0.50, "beats": True},
            "random": {"estimate": -0.41, "beats": False}}
    assert default_choice(runs, {"farthest": {"beats": False}, "fisher": {"beats": False}}) == "hpgs"
    assert default_choice(runs, {"farthest": {"beats": True}, "fisher": {"beats": False}}) == "farthest"
    assert default_choice(runs, {"farthest": {"beats": True}, "fisher": {"beats": True}}) == "fisher"
    # beaten by its final-sets alone is not enough
    assert default_choice({"fisher": {"estimate": 0.5, "beats": False}}, {"fisher": {"beats": True}}) == "hpgs"
    # a selector beaten *by* hpgs never counts, whatever its interval
    worse = gains_over([comparison("hpgs", "random", 1.0, 0.5, 1.5, 0.001)], "hpgs")
    assert worse["random"]["estimate"] == -1.0 and not worse["random"]["beats"]
