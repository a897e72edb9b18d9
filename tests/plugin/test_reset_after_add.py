"""`--pipeline.model.restarts.every-round` (FisherRF's protocol) on the tiny scene with the CPU rasterizer.

Densification is set to start at step 40 (splatfacto pauses refinement for num_train_data + refine_every steps
after each opacity reset, step 0 included), so by the round at step 50 the splat has grown and the reset
visibly takes it back. A run without the option, and a resume across a second round, are checked beside it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from conftest import run_training_seeing, short_config

ROUND, SECOND_ROUND = 50, 62
CAPTURE = {0, 1, ROUND - 1, ROUND, ROUND + 1, 59, 60, SECOND_ROUND}


def reset_config(scene: Path, out: Path, steps: int, reset: bool = True):
    cfg = short_config(scene, out, steps=steps, select_at=(ROUND, SECOND_ROUND), rounds=2)
    model = cfg.pipeline.model
    model.restarts.every_round = reset
    model.warmup_length, model.refine_every, model.reset_alpha_every = 5, 5, 100  # first refinement at step 40
    model.camera_optimizer.mode = "SO3xR3"  # so the camera optimizer's reset is checked too
    return cfg


def see(trainer, step) -> dict:
    """What the iteration at `step` sees (after the round and the model's step callback)."""
    model, opts = trainer.pipeline.model, trainer.optimizers
    seen = {
        "num_points": model.num_points,
        "model_step": model.step,
        "lr": {k: o.param_groups[0]["lr"] for k, o in opts.optimizers.items()},
        "adam_states": sum(len(o.state) for o in opts.optimizers.values()),
        "last_epoch": opts.schedulers["means"].last_epoch,
        "grad2d": model.strategy_state["grad2d"],
        "pose": model.camera_optimizer.pose_adjustment.detach().clone(),
    }
    if step in CAPTURE:
        seen["gauss"] = {k: v.detach().clone() for k, v in model.gauss_params.items()}
    return seen


def train_with_spy(cfg) -> dict:
    trainer, seen = run_training_seeing(cfg, see)
    return {"trainer": trainer, "seen": seen, "run_dir": Path(trainer.base_dir)}


@pytest.fixture(scope="module")
def with_reset(tiny_scene, tmp_path_factory):
    return train_with_spy(reset_config(tiny_scene, tmp_path_factory.mktemp("reset"), steps=60))


@pytest.fixture(scope="module")
def without_reset(tiny_scene, tmp_path_factory):
    return train_with_spy(reset_config(tiny_scene, tmp_path_factory.mktemp("noreset"), steps=ROUND + 2, reset=False))


def assert_same_gaussians(a, b):
    assert a.keys() == b.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), name


def test_round_puts_the_initial_gaussians_back(with_reset):
    seen = with_reset["seen"]
    assert seen[0]["num_points"] == 1500
    assert seen[ROUND - 1]["num_points"] > 2000  # densified at steps 40 and 45
    assert seen[ROUND]["num_points"] == 1500
    assert_same_gaussians(seen[ROUND]["gauss"], seen[0]["gauss"])
    assert seen[ROUND + 1]["num_points"] == 1500  # refinement restarts at local step 40, not global 55


def test_optimizer_and_strategy_state_start_fresh(with_reset):
    seen = with_reset["seen"]
    assert seen[ROUND - 1]["adam_states"] == 7 and seen[ROUND - 1]["grad2d"] is not None
    assert seen[ROUND]["adam_states"] == 0 and seen[ROUND]["grad2d"] is None
    assert seen[ROUND + 1]["adam_states"] == 7 and seen[ROUND + 1]["grad2d"].shape == (1500,)
    assert seen[ROUND - 1]["pose"].abs().max() > 0
    assert torch.equal(seen[ROUND]["pose"], torch.zeros(35, 6))


def test_schedules_restart_at_the_round_step(with_reset):
    seen = with_reset["seen"]
    assert seen[ROUND]["lr"] == seen[0]["lr"] and seen[ROUND + 1]["lr"] == seen[1]["lr"]
    assert seen[ROUND]["lr"]["means"] == 1.6e-4
    assert seen[ROUND - 1]["lr"]["means"] == pytest.approx(1.6e-4 * 0.01 ** (49 / 60))  # decayed before the reset
    assert [seen[s]["model_step"] for s in (ROUND - 1, ROUND, 59)] == [49, 0, 9]
    assert seen[59]["last_epoch"] == 9


def test_run_ends_at_the_configured_step_and_logs_the_reset(with_reset):
    trainer = with_reset["trainer"]
    assert trainer.step == 59 and max(with_reset["seen"]) == 59
    log = json.loads((with_reset["run_dir"] / "selected_views.json").read_text())
    assert log["reset_after_add"] is True
    (record,) = log["rounds"]
    assert record["step"] == ROUND and record["reset"] is True
    assert record["num_gaussians_before_reset"] == with_reset["seen"][ROUND - 1]["num_points"]
    assert record["num_gaussians_after_reset"] == 1500


def test_checkpoint_keeps_the_offset_and_initial_gaussians(with_reset):
    (ckpt,) = sorted((with_reset["run_dir"] / "nerfstudio_models").glob("step-*59.ckpt"))
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    extra = state["pipeline"]["_model._extra_state"]
    assert extra["step_offset"] == ROUND
    assert_same_gaussians(extra["initial_gaussians"], with_reset["seen"][0]["gauss"])
    assert state["schedulers"]["means"]["last_epoch"] == 10


def test_resume_continues_the_restarted_schedule_and_resets_to_the_saved_gaussians(with_reset, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(with_reset["run_dir"], copy)
    cfg = reset_config(with_reset["trainer"].config.data, tmp_path / "resumed", steps=70)
    cfg.load_dir = copy / "nerfstudio_models"
    resumed = train_with_spy(cfg)
    seen = resumed["seen"]
    assert min(seen) == 60 and resumed["trainer"].step == 69
    assert seen[60]["model_step"] == 10 and seen[60]["last_epoch"] == 10  # not restarted, not global
    assert seen[SECOND_ROUND]["model_step"] == 0 and seen[SECOND_ROUND]["lr"]["means"] == 1.6e-4
    # The resumed model built fresh (random) quaternions; the reset must use the checkpoint's step-0 ones.
    assert_same_gaussians(seen[SECOND_ROUND]["gauss"], with_reset["seen"][0]["gauss"])
    history = resumed["trainer"].pipeline.datamanager.history
    assert [(h.step, h.reset) for h in history] == [(ROUND, True), (SECOND_ROUND, True)]


def test_without_the_option_training_continues(without_reset):
    seen = without_reset["seen"]
    assert seen[ROUND - 1]["num_points"] > 2000
    assert seen[ROUND]["num_points"] == seen[ROUND - 1]["num_points"]
    assert seen[ROUND]["model_step"] == ROUND and seen[ROUND]["adam_states"] == 7
    assert seen[ROUND]["lr"]["means"] == pytest.approx(1.6e-4 * 0.01 ** (ROUND / (ROUND + 2)))
    log = json.loads((without_reset["run_dir"] / "selected_views.json").read_text())
    assert log["reset_after_add"] is False and log["rounds"][0]["reset"] is False
    assert "num_gaussians_before_reset" not in log["rounds"][0]
    assert without_reset["trainer"].pipeline.model.step_offset == 0
