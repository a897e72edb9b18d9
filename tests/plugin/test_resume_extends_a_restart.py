"""`--load-dir` with a longer `--max-num-iterations` after a run restarted (issue #65, item 2): the extended run's
learning rates, and the model's squeezed step-keyed schedule, are those of an uninterrupted run of the new length
that restarted at the same step, not the checkpoint's schedule that ended at its old last step."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import run_training, run_training_seeing, short_config

SHORT, LONG = 30, 45  # steps; the rounds at 5 and 10, the restart at 10


def config(scene: Path, out: Path, steps: int):
    """2 initial views, one added at steps 5 and 10: the default restart-seeded-starts restarts at 4 views (step 10)."""
    return short_config(scene, out, steps=steps, every=5, rounds=2, initial=2, selector="random")


def rates(trainer, step):
    """Every optimizer's learning rate (the means' decays; the camera optimizer's warms up, then decays)."""
    return {name: o.param_groups[0]["lr"] for name, o in trainer.optimizers.optimizers.items()}


def test_extending_a_run_that_restarted_follows_the_uninterrupted_longer_run(tiny_scene, tmp_path, capsys):
    torch.manual_seed(0)
    whole, whole_rates = run_training_seeing(config(tiny_scene, tmp_path / "whole", LONG), rates)
    torch.manual_seed(0)
    first = run_training(config(tiny_scene, tmp_path / "first", SHORT))
    restarts = [h.step for h in first.pipeline.datamanager.history if h.reset]
    assert restarts == [10] == [h.step for h in whole.pipeline.datamanager.history if h.reset]
    capsys.readouterr()
    cfg = config(tiny_scene, tmp_path / "longer", LONG)
    cfg.load_dir = Path(first.base_dir) / "nerfstudio_models"
    longer, longer_rates = run_training_seeing(cfg, rates)
    out = " ".join(capsys.readouterr().out.split())
    assert f"the learning-rate schedules now end at step {LONG} (the checkpoint's ended at step {SHORT})" in out
    assert sorted(longer_rates) == list(range(SHORT, LONG))
    for step in range(SHORT, LONG):
        assert longer_rates[step] == pytest.approx(whole_rates[step], rel=1e-9), step
    floor = whole.config.optimizers["means"]["scheduler"].lr_final
    assert longer_rates[SHORT]["means"] > 3 * floor  # the old code held it at the floor from the old end on
    # splatfacto's step-keyed schedule (densification, SH degree) is squeezed into the steps after the restart too
    assert longer.pipeline.model.clock_scale == pytest.approx(whole.pipeline.model.clock_scale) == (LONG - 10) / LONG
