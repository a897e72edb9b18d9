"""The early-stop calibration (`hpgs_lab.gain_fit`): the gain of a view measured against the `initial` reference,
and the gain model fitted and judged leave one scene out. The run-time part (a run that stops selecting) is the
plugin's: tests/plugin/test_early_stop.py."""

from __future__ import annotations

import math

import pytest
from helpers import make_result

from hpgs_lab.gain_fit import early_stop_curve, fit_gain_model, round_gains, view_gains
from hpgs_lab.results import RoundPsnr
from hpgs_ns.selection.early_stop import GainModel


def runs(scene: str, a: float, b: float, seed: int = 0, initial_views=None) -> list:
    """A selector run whose k-th view gains exactly a + b log(views), and its `initial` reference, which gains
    0.3 dB of training per round whatever the views (the confound the reference removes)."""
    steps = [400, 900, 1500, 2200]
    views = [4, 5, 6, 7]
    ref = {s: 15.0 + 0.3 * k for k, s in enumerate(steps)}
    g, sel = 0.0, {}
    for k, s in enumerate(steps):
        sel[s] = ref[s] + g
        g += a + b * math.log(views[k])
    initial = initial_views or [f"{seed}.jpg"]
    return [
        make_result(scene, "fisherrf", "initial", seed, 15.0 + 0.3 * 4, initial_views=initial, psnr_at_round_steps=ref),
        make_result(scene, "fisherrf", "fisher", seed, 15.0 + 0.3 * 4 + g, initial_views=initial, psnr_at_round_steps=sel,
                    num_views_final=8, psnr_per_round=[RoundPsnr(s, v, sel[s]) for s, v in zip(steps, views)]),
    ]


def test_a_views_gain_is_measured_against_the_reference_at_the_same_steps():
    rows = runs("s", 1.0, -0.4)
    gains = round_gains(rows)
    assert [(v, round(g, 9)) for _, _, v, g in gains] == [(v, round(1.0 - 0.4 * math.log(v), 9)) for v in (4, 5, 6, 7)]
    assert view_gains(rows)[0].G[0] == 0.0  # before the first round: the same views as the reference
    assert round_gains(runs("s", 1.0, -0.4)[1:]) == []  # no reference, no gain


def test_a_reference_of_another_seed_serves_only_a_run_from_the_same_initial_views():
    ref = runs("s", 1.0, -0.4, seed=0, initial_views=["a.jpg", "b.jpg"])[0]
    same = runs("s", 1.0, -0.4, seed=1, initial_views=["a.jpg", "b.jpg"])[1]
    other = runs("s", 1.0, -0.4, seed=2, initial_views=["a.jpg", "c.jpg"])[1]
    gains = view_gains([ref, same, other])
    assert [v.run.seed for v in gains] == [1]
    assert gains[0].G[0] == 0.0


def test_the_calibration_is_recovered_and_judged_leaving_one_scene_out(tmp_path):
    rows = runs("s1", 1.0, -0.4) + runs("s2", 1.0, -0.4) + runs("s3", 1.0, -0.4, seed=1)
    model = fit_gain_model(rows)
    a, b = model.coefficients["fisher"]
    assert (a, b) == pytest.approx((1.0, -0.4)) and model.fitted_on == ["s1", "s2", "s3"]
    assert model.predict("hpgs", 4) == pytest.approx(1.0 - 0.4 * math.log(4))  # unknown selector: the average
    model.save(tmp_path / "m.json")
    assert GainModel.load(tmp_path / "m.json").coefficients["fisher"] == pytest.approx((1.0, -0.4))
    # 0.3 dB: views 4 -> 0.45, 5 -> 0.36, 6 -> 0.28: stop before the 3rd round, losing what rounds 3-4 gained
    [never, at_03] = early_stop_curve(rows, [-1.0, 0.3])
    assert never["views_saved"] == 0 and never["psnr_lost_db"] == 0
    assert at_03["views_saved"] == 2 and at_03["psnr_lost_db"] == pytest.approx(2 - 0.4 * (math.log(6) + math.log(7)))
    with pytest.raises(ValueError, match="an `initial` reference"):
        fit_gain_model([r for r in rows if r.selector != "initial"])
