"""stop-when-gain-below: the gain of a view measured against the `initial` reference, its calibration (fitted and
judged leave one scene out), and a run that stops selecting when the next view is predicted to gain too little."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from conftest import run_training, short_config

from hpgs_ns.errors import UserError
from hpgs_ns.selection.early_stop import GainModel


def test_a_run_stops_selecting_when_the_next_view_gains_too_little(tiny_scene, tmp_path):
    model = tmp_path / "gain.json"
    GainModel({"*": (4.0, -2.0)}, ["x"]).save(model)  # 4 - 2 log(views): 0.4 dB at 6 views, 0.1 at 7, < 0 at 8
    cfg = short_config(tiny_scene, tmp_path / "run", steps=70, every=20, rounds=3, selector="farthest",
                       stop_when_gain_below=0.2, gain_model=model, eval_each_round=True)
    trainer = run_training(cfg)
    log = json.loads((Path(trainer.base_dir) / "selected_views.json").read_text())
    assert [r["step"] for r in log["rounds"]] == [20] and len(log["active"]) == 7
    assert log["stopped"]["step"] == 40 and log["stopped"]["views"] == 7
    assert log["stopped"]["predicted_gain_db"] == pytest.approx(4 - 2 * math.log(7))
    # the test PSNR is still recorded where no round ran (what a reference run records)
    assert list(log["test_psnr_at_round_steps"]) == ["20", "40", "60"]


def test_a_missing_gain_model_is_a_one_line_error(tmp_path):
    with pytest.raises(UserError, match="no gain model at .*nope.json: pass --pipeline.selection.gain-model FILE"):
        GainModel.load(tmp_path / "nope.json")


def test_the_shipped_gain_model_is_the_suites_and_predicts_less_per_view_as_views_grow():
    model = GainModel.load()  # hpgs_ns/assets/gain-model.json
    assert set(model.fitted_on) == {"bonsai", "campus-building", "fox", "juicebox", "mold-gold-cape", "stitch"}
    assert {"*", "random", "farthest", "fisher", "hpgs"} <= set(model.coefficients)
    for selector in ("*", "farthest", "fisher", "hpgs", "condorcet"):  # condorcet: no runs, the average
        gains = [model.predict(selector, v) for v in (4, 10, 19)]
        assert gains[0] > gains[1] > gains[2] > 0 and gains[0] < 1.0  # every view still pays up to 20, less and less
