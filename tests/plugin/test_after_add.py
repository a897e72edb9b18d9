"""`--pipeline.selection.after-add.*` on the tiny scene with the CPU rasterizer: after the round at step 50,
densification runs again although stop-split-at (45) has passed, opacities are reset, and the means' learning rate
is rewound 30 steps; the state survives `--load-dir`.

Refinement: every 5 steps from step 40 (splatfacto pauses it for num_train_data + refine_every = 40 steps after the
step-0 opacity reset), so the only refine before the add is at step 40."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from conftest import run_training_seeing, short_config

from hpgs_ns.selection.after_add import AfterAddConfig, AfterAddError, rewind_schedules

ROUND, STOP, TOTAL, REWIND, WINDOW = 50, 56, 80, 30, 20


def after_add_config(scene: Path, out: Path, steps: int):
    cfg = short_config(scene, out, steps=TOTAL, select_at=(ROUND,), rounds=1, selector="random")
    cfg.max_num_iterations, cfg.schedules_follow_steps = steps, steps == TOTAL  # a stopped run keeps TOTAL's schedule
    model = cfg.pipeline.model
    model.warmup_length, model.refine_every, model.reset_alpha_every, model.stop_split_at = 5, 5, 100, 45
    model.stop_screen_size_at = 30
    cfg.pipeline.selection.after_add = AfterAddConfig(refine_steps=WINDOW, reset_opacity=True, lr_rewind=REWIND)
    return cfg


def see(trainer, step) -> dict:
    model = trainer.pipeline.model
    return {"num_points": model.num_points, "lr": trainer.optimizers.optimizers["means"].param_groups[0]["lr"],
            "position": trainer.optimizers.schedulers["means"].last_epoch,
            "max_opacity": float(model.gauss_params["opacities"].max()),
            "refine_stop": model.strategy.refine_stop_iter,
            "screen_size_stop": model.strategy.refine_scale2d_stop_iter}


def train_with_spy(cfg, seen: dict):
    trainer, steps = run_training_seeing(cfg, see)
    seen.update(steps)
    return trainer


@pytest.fixture(scope="module")
def run(tiny_scene, tmp_path_factory):
    seen: dict = {}
    torch.manual_seed(0)
    first = train_with_spy(after_add_config(tiny_scene, tmp_path_factory.mktemp("first"), STOP), seen)
    copy = tmp_path_factory.mktemp("copy") / "run"
    shutil.copytree(first.base_dir, copy)
    cfg = after_add_config(tiny_scene, tmp_path_factory.mktemp("resumed"), TOTAL)
    cfg.load_dir = copy / "nerfstudio_models"
    resumed = train_with_spy(cfg, seen)
    return {"seen": seen, "first": first, "resumed": resumed}


def test_refinement_stops_at_stop_split_at_then_runs_again_after_the_add(run):
    seen = run["seen"]
    counts = [seen[s]["num_points"] for s in range(41, ROUND + 1)]
    assert len(set(counts)) == 1  # no refine between stop-split-at and the add
    assert seen[ROUND - 1]["refine_stop"] == 45 and seen[ROUND]["refine_stop"] == ROUND + WINDOW
    # the screen-size split and cull (a floater filling the new view's screen) open again for the same window
    assert seen[ROUND - 1]["screen_size_stop"] == 30 and seen[ROUND]["screen_size_stop"] == ROUND + WINDOW
    assert seen[TOTAL - 1]["screen_size_stop"] == ROUND + WINDOW  # after the resume too
    # refines at 55 (before the resume), 60 and 65 (after it): the count moves, then stays after the window
    assert len({seen[s]["num_points"] for s in range(ROUND + 1, ROUND + WINDOW + 1)}) > 1
    assert len({seen[s]["num_points"] for s in range(ROUND + WINDOW + 1, TOTAL)}) == 1


def test_opacities_are_reset_at_the_add(run):
    seen = run["seen"]
    cap = torch.logit(torch.tensor(0.1 * 2.0)).item()  # splatfacto's cull_alpha_thresh 0.1, reset to twice it
    assert seen[ROUND - 1]["max_opacity"] > cap + 0.5
    assert seen[ROUND]["max_opacity"] == pytest.approx(cap, abs=1e-5)


def test_the_means_learning_rate_is_rewound_and_the_rewind_survives_a_resume(run):
    seen = run["seen"]
    assert seen[ROUND - 1]["position"] == ROUND - 1 and seen[ROUND]["position"] == ROUND - REWIND
    assert seen[ROUND]["lr"] == pytest.approx(seen[ROUND - REWIND]["lr"], rel=1e-9)
    assert seen[STOP]["position"] == STOP - REWIND  # first step after the resume: the rewound clock went on
    assert seen[STOP]["refine_stop"] == ROUND + WINDOW


def test_the_round_log_records_what_was_done(run):
    log = json.loads((Path(run["resumed"].base_dir) / "selected_views.json").read_text())
    done = log["rounds"][0]["after_add"]
    assert done["refine_until"] == ROUND + WINDOW and done["lr_position.means"] == ROUND - REWIND
    assert done["opacity_reset"] > 0


def test_rewind_never_goes_before_the_start_and_bad_values_are_one_line():
    params = [torch.nn.Parameter(torch.zeros(1))]
    optimizer = torch.optim.Adam(params, lr=1.0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 0.5 ** step)
    for _ in range(3):
        scheduler.step()
    assert rewind_schedules({"means": scheduler}, 2) == {"means": 1} and optimizer.param_groups[0]["lr"] == 0.5
    assert rewind_schedules({"means": scheduler}, 10) == {"means": 0} and optimizer.param_groups[0]["lr"] == 1.0
    with pytest.raises(AfterAddError, match="refine-steps -1 must be a whole number"):
        AfterAddConfig(refine_steps=-1)
    assert AfterAddConfig().describe() == "off" and not AfterAddConfig().enabled


def test_lr_restart_starts_every_schedule_over_and_still_ends_at_the_floor_rate():
    from hpgs_ns.schedules import DecayMultiplier
    from hpgs_ns.selection.after_add import apply_after_add

    class Optimizers:  # what apply_after_add reads of nerfstudio's Optimizers
        def __init__(self, schedulers):
            self.schedulers = schedulers

    params = [torch.nn.Parameter(torch.zeros(1))]
    optimizer = torch.optim.Adam(params, lr=1e-2)
    decay = DecayMultiplier(lr_init=1e-2, lr_final=1e-4, lr_pre_warmup=1e-2, warmup_steps=0, max_steps=80)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, decay)
    for _ in range(50):
        scheduler.step()
    assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-2 * 0.01 ** (50 / 80))
    done = apply_after_add(AfterAddConfig(lr_restart=True), None, Optimizers({"means": scheduler}), step=50, end=80)
    assert done == {"lr_restart_span": 30.0} and optimizer.param_groups[0]["lr"] == pytest.approx(1e-2)
    for _ in range(15):  # half-way through the 30 steps left: half-way down the decay (geometric)
        scheduler.step()
    assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    for _ in range(15):
        scheduler.step()
    assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-4)  # at the run's end: the floor rate
    with pytest.raises(AfterAddError, match="lr-restart and lr-rewind"):
        AfterAddConfig(lr_restart=True, lr_rewind=10)
    assert AfterAddConfig(lr_restart=True).describe() == "lr-restart True" and AfterAddConfig(lr_restart=True).enabled


def test_lr_restart_runs_at_the_rounds_add_and_the_run_ends_at_the_floor_rate(tiny_scene, tmp_path):
    cfg = short_config(tiny_scene, tmp_path, steps=TOTAL, select_at=(ROUND,), rounds=1, selector="random")
    cfg.pipeline.selection.after_add = AfterAddConfig(lr_restart=True)
    seen: dict = {}
    trainer = train_with_spy(cfg, seen)
    log = json.loads((Path(trainer.base_dir) / "selected_views.json").read_text())
    assert log["rounds"][0]["after_add"] == {"lr_restart_span": TOTAL - ROUND}
    schedule = trainer.optimizers.schedulers["means"].lr_lambdas[0]
    initial, final = schedule.lr_init, schedule.lr_final
    assert seen[ROUND - 1]["lr"] == pytest.approx(initial * (final / initial) ** ((ROUND - 1) / TOTAL))
    assert seen[ROUND]["lr"] == pytest.approx(initial)  # back to the start at the add
    assert trainer.optimizers.optimizers["means"].param_groups[0]["lr"] == pytest.approx(final)
