"""benchmarks/trainer_arms.py: a trainer pilot's arm against `off`, paired by (scene, selector, seed); and
benchmarks/plot_pilot_curves.py's mean curve over a pilot's runs."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from helpers import make_result

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture()
def pilots():
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import plot_pilot_curves
        import trainer_arms
        yield SimpleNamespace(compare=trainer_arms.compare, mean_curve=plot_pilot_curves.mean_curve,
                              peaks=plot_pilot_curves.peaks)
    finally:
        sys.path.remove(str(REPO / "benchmarks"))


def write(root: Path, arm: str, scene: str, selector: str, seed: int, run: float, final: float, wall: float = 100.0):
    from hpgs_lab.results import SourceRun

    folder = root / "auto" / arm / scene / "fisherrf" / selector
    views = {"initial_views": ["v0"], "chosen_views": ["v1"], "num_views_final": 2}
    make_result(scene, "fisherrf", selector, seed, run, wall=wall, **views).to_json(folder / f"seed{seed}.json")
    make_result(scene, "fisherrf", "final-set", seed, final, wall=wall, final_set_of=SourceRun(selector, seed, 0, ["v0", "v1"]),
                **views).to_json(folder / "final-set" / f"seed{seed}.json")


def test_an_arm_is_paired_with_off_and_judged_by_the_plans_rule(tmp_path, pilots):
    # off: schedule cost 1.0 everywhere; arm: runs +0.5 (a), +0.3 (b) higher, final-sets unchanged -> cost 0.5 / 0.7
    for scene, up in (("a", 0.5), ("b", 0.3)):
        for sel in ("random", "hpgs"):
            for seed in (0, 1):
                write(tmp_path, "off", scene, sel, seed, 20.0 + seed, 21.0 + seed)
                write(tmp_path, "r16", scene, sel, seed, 20.0 + seed + up, 21.0 + seed, wall=110.0)
    write(tmp_path, "r16", "c", "random", 0, 30.0, 31.0)  # no off run to pair with: left out
    out = pilots.compare(tmp_path / "auto", "off", "r16")
    assert out["gain"]["pairs"] == 8 and out["gain"]["mean"] == pytest.approx(0.4)
    assert out["gain_by_selector"]["hpgs"]["mean"] == pytest.approx(0.4)
    assert out["schedule_cost"]["off/random"]["mean"] == pytest.approx(1.0)
    assert out["schedule_cost"]["r16/hpgs"]["mean"] == pytest.approx(0.6)
    assert out["random_final_set_difference"]["mean"] == pytest.approx(0.0)
    assert out["run_wall_s"] == {"off": 100.0, "r16": 110.0}
    assert out["per_scene_gain"] == {"a": 0.5, "b": 0.3}
    # two scenes both up: the exact sign-flip p over 2 scene means is 2/4 = 0.5, so the rule (p < 0.1) is not met
    assert out["gain"]["p"] == pytest.approx(0.5) and out["decision"] == "rule not met"


def test_the_mean_curve_averages_each_step_and_ends_with_the_runs_final_psnr(pilots):
    runs = [make_result("a", "fisherrf", "random", 0, 18.0, steps=1000, psnr_at_round_steps={200: 15.0, 600: 16.0}),
            make_result("b", "fisherrf", "random", 0, 20.0, steps=1000, psnr_at_round_steps={200: 17.0, 600: 15.0})]
    assert pilots.mean_curve(runs) == {200: 16.0, 600: 15.5, 1000: 19.0}


def test_peaks_finds_where_a_scenes_final_sets_score_best_and_what_the_end_loses(pilots):
    early = [make_result("a", "fisherrf", "final-set", seed, end, steps=1000, psnr_at_round_steps={200: 18.0 + seed, 600: 16.0})
             for seed, end in ((0, 15.0), (1, 15.5))]
    late = [make_result("b", "fisherrf", "final-set", 0, 22.0, steps=1000, psnr_at_round_steps={200: 19.0, 600: 21.0})]
    old = [make_result("c", "fisherrf", "final-set", 0, 25.0, steps=1000)]  # no round steps: left out
    out = pilots.peaks(early + late + old)
    # a: mean curve 200 -> 18.5, 600 -> 16.0, end 15.25; b keeps improving to its end
    assert out["a"] == {"best_step": 200, "best_minus_end": 3.25, "end": 15.25, "final_sets": 2}
    assert out["b"] == {"best_step": 1000, "best_minus_end": 0.0, "end": 22.0, "final_sets": 1}
    assert "c" not in out
