"""`--pipeline.model.restarts.*` and `--schedules-follow-steps` on the tiny scene (CPU rasterizer).

A random start (random-init) from 3 initial views, 3 views added at steps 30 and 50 of 80: with the defaults
(random-starts), the round at step 30 (3 -> 6 views, twice the initial count) starts the splat over with 50
of the 80 steps left, so every schedule runs 80/50 = 1.6 times faster from there; the round at step 50 (6 -> 9)
does not restart (the next count is 12)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch
from conftest import run_training_seeing, short_config

from hpgs_ns.schedules import DecayMultiplier
from hpgs_ns.strategies.restarts import RestartError, RestartsConfig

RESTART, SECOND, TOTAL = 30, 50, 80
LEFT = TOTAL - RESTART


def see(trainer, step) -> dict:
    m = trainer.pipeline.model
    return {"num_points": m.num_points, "lr": trainer.optimizers.optimizers["means"].param_groups[0]["lr"],
            "model_step": m.step, "refine_every": m.strategy.refine_every, "refine_stop": m.strategy.refine_stop_iter,
            "sh": m.active_sh_degree, "means": float(m.gauss_params["means"].detach().double().sum())}


@pytest.fixture(scope="module")
def run(tiny_scene, tmp_path_factory):
    cfg = short_config(tiny_scene, tmp_path_factory.mktemp("restart"), steps=TOTAL, select_at=(RESTART, SECOND),
                       rounds=2, initial=3, views_per_round=3, selector="random")
    model = cfg.pipeline.model
    model.warmup_length, model.refine_every, model.reset_alpha_every, model.stop_split_at = 10, 10, 100, 60
    model.random_init, model.num_random = True, 1500
    torch.manual_seed(0)
    trainer, seen = run_training_seeing(cfg, see)
    return {"seen": seen, "trainer": trainer, "cfg": cfg}


def test_schedules_follow_the_run_length(run):
    trainer = run["trainer"]
    assert trainer.config.optimizers["means"]["scheduler"].max_steps == TOTAL
    assert trainer.optimizers.schedulers["means"].lr_lambdas[0].max_steps == TOTAL
    # the method's default config (shared by every parse) keeps 15000
    from hpgs_ns.method_config import hpgs
    assert hpgs.config.optimizers["means"]["scheduler"].max_steps == 15000


def test_old_schedule_when_following_is_off():
    from hpgs_ns.method_config import hpgs_trainer_config
    from hpgs_ns.trainer import follow_run_length

    cfg = hpgs_trainer_config(300)
    cfg.max_num_iterations = 20000
    cfg.schedules_follow_steps = False
    follow_run_length(cfg)
    assert cfg.optimizers["means"]["scheduler"].max_steps == 300
    cfg.schedules_follow_steps = True
    follow_run_length(cfg)
    assert cfg.optimizers["means"]["scheduler"].max_steps == 20000


def test_the_restart_round_puts_the_initial_gaussians_back(run):
    seen, model = run["seen"], run["trainer"].pipeline.model
    initial = model.initial_gaussians["means"]
    assert seen[RESTART - 1]["means"] != pytest.approx(float(initial.double().sum()), abs=1e-6)  # trained
    assert seen[RESTART]["means"] == pytest.approx(float(initial.double().sum()), abs=1e-6)
    assert seen[RESTART]["num_points"] == initial.shape[0]
    assert seen[RESTART]["model_step"] == 0 and seen[RESTART + 7]["model_step"] == 7


def test_the_schedules_run_faster_in_the_steps_left(run):
    seen, model = run["seen"], run["trainer"].pipeline.model
    assert model.clock_scale == pytest.approx(LEFT / TOTAL)
    # refine every 10 steps -> every round(10 x 50/80) = 6; stop-split-at 60 -> 38 model steps after the restart
    assert seen[RESTART - 1]["refine_every"] == 10 and seen[RESTART]["refine_every"] == 6
    assert seen[RESTART]["refine_stop"] == 38
    # SH degree steps every 20 -> 12 model steps: degree 1 at model step 12, as at trainer step 20 before
    assert seen[RESTART + 11]["sh"] == 0 and seen[RESTART + 12]["sh"] == 1
    # the means' rate k steps after the restart is the full-run schedule's at k x 80/50
    base = DecayMultiplier(lr_init=1.6e-4, lr_final=1.6e-6, lr_pre_warmup=1e-8, warmup_steps=0, max_steps=TOTAL)
    for k in (1, 10, 25, LEFT - 1):
        assert seen[RESTART + k]["lr"] == pytest.approx(1.6e-4 * base(k * TOTAL / LEFT), rel=1e-6)
    assert seen[RESTART + 10]["lr"] < seen[10]["lr"]


def test_only_twice_the_initial_count_restarts_and_the_log_says_so(run):
    seen = run["seen"]
    assert run["trainer"].pipeline.model.random_start
    assert seen[SECOND]["model_step"] == SECOND - RESTART  # 6 -> 9 views: no restart
    log = json.loads((Path(run["trainer"].base_dir) / "selected_views.json").read_text())
    assert [bool(r.get("reset")) for r in log["rounds"]] == [True, False]


def test_the_squeezed_clocks_are_in_the_checkpoint(run):
    trainer = run["trainer"]
    model = trainer.pipeline.model
    state = model.get_extra_state()
    assert state["clock_scale"] == pytest.approx(LEFT / TOTAL) and state["step_offset"] == RESTART
    model.set_clock_scale(1.0)
    model.set_extra_state(state)
    assert model.strategy.refine_every == 6
    scheduler = trainer.optimizers.schedulers["means"]
    saved = scheduler.state_dict()
    scheduler.lr_lambdas[0].speed = 1.0
    scheduler.load_state_dict(saved)
    assert scheduler.lr_lambdas[0].speed == pytest.approx(TOTAL / LEFT)


def test_restart_counts_must_be_positive():
    with pytest.raises(RestartError, match=r"--pipeline.model.restarts.at-views 0 8: view counts must be >= 1"):
        RestartsConfig(at_views=(0, 8))
    config = RestartsConfig(at_views=(8, 16))
    assert config.describe_restarts() == "restart-at-views 8 16"  # 0.4's words: checkpoints hold them
    assert config.restart_counts(4, random_start=False) == (8, 16)
    auto = RestartsConfig()
    assert auto.restart_counts(4, random_start=True) == (8, 16) and auto.restart_counts(4, random_start=False) == (8, 16)
    assert auto.describe_restarts() == "off" and not RestartsConfig(random_starts=False).restart_counts(4, True)
    # an active start that found its points restarts too, unless told not to; HP-GS's 20 + 7 views never reach 40
    assert auto.restart_counts(4, random_start=False, active_start=True) == (8, 16)
    assert RestartsConfig(active_starts=False).restart_counts(4, False, active_start=True) == ()
    assert RestartsConfig(active_starts=False).restart_counts(4, True, active_start=False) == (8, 16)
    assert auto.restart_counts(20, False, active_start=True) == (40, 80)
    # a start from the capture's points restarts too by default (restart-seeded-starts), and only as such; 0.4's
    # trainer (never) is one flag away
    unseeded = RestartsConfig(seeded_starts=False)
    assert unseeded.signature("colmap", random_start=False) == {
        "after-add": "off", "reset-after-add": "False", "after-add.restart-seeded-starts": "False"}
    assert unseeded.restart_counts(4, random_start=False) == ()
    assert unseeded.restart_counts(4, random_start=True) == unseeded.restart_counts(4, False, True) == (8, 16)
    assert RestartsConfig(active_starts=False).restart_counts(4, False, True) == ()
    assert RestartsConfig(random_starts=False).restart_counts(4, True) == ()
    assert auto.restart_counts(20, random_start=False, final_views=27) == ()  # HP-GS's 20 + 7: never


def test_restart_counts_end_with_the_runs_final_views():
    assert RestartsConfig().restart_counts(4, random_start=True, final_views=12) == (8,)
    assert RestartsConfig().restart_counts(4, random_start=False, final_views=20) == (8, 16)  # seeded
    assert RestartsConfig(seeded_starts=False).restart_counts(4, random_start=False, final_views=20) == ()
    assert RestartsConfig(at_views=(8, 20)).restart_counts(4, False, final_views=20) == (8, 20)
    assert RestartsConfig().restart_counts(4, random_start=False, final_views=4) == ()  # no round adds views


def test_restart_options_that_do_nothing_say_so_at_start(capsys):
    from types import SimpleNamespace

    from hpgs_ns.strategies.base import RoundsPlan

    def said(config: RestartsConfig, final_views: int) -> str:
        model = SimpleNamespace(random_start=False, keep_initial_for_resets=lambda: None)
        config.setup().plan(model, RoundsPlan(initial_views=4, final_views=final_views, seed_points="colmap"))
        return " ".join(capsys.readouterr().out.split())

    assert said(RestartsConfig(at_views=(8,), every_round=True), 20) == (
        "--pipeline.model.restarts.at-views does nothing with --pipeline.model.restarts.every-round: the splat "
        "restarts after every round")
    assert said(RestartsConfig(at_views=(30, 40)), 20) == (
        "--pipeline.model.restarts.at-views 30 40 does nothing: this run goes from 4 to 20 views")
    assert said(RestartsConfig(at_views=(8, 40)), 20) == ""  # 8 comes: nothing to say (the counts are the user's)
    assert said(RestartsConfig(), 20) == ("seed points: the splat restarts at 8 and 16 views from the capture's "
                                          "points (--pipeline.model.restarts.seeded-starts False: never)")


def seeded_run(tiny_scene, folder: Path, restarts: RestartsConfig, capsys):
    """A run from the synthetic scene's points (3 initial views, 3 more at steps 20 and 30 of 40) with `restarts`:
    (trainer, what `see` saw each step, the rounds' log, the console's start-up text on one line)."""
    cfg = short_config(tiny_scene, folder, steps=40, select_at=(20, 30), rounds=2, initial=3, views_per_round=3,
                       selector="random")
    cfg.pipeline.model.restarts = restarts
    torch.manual_seed(0)
    trainer, seen = run_training_seeing(cfg, see)
    assert not trainer.pipeline.model.random_start  # the synthetic scene's points: no automatic restarts
    log = json.loads((Path(trainer.base_dir) / "selected_views.json").read_text())
    return trainer, seen, [bool(r.get("reset")) for r in log["rounds"]], " ".join(capsys.readouterr().out.split())


def test_a_seeded_run_restarts_where_restart_at_views_says(tiny_scene, tmp_path, capsys):
    restarts = RestartsConfig(at_views=(9,), seeded_starts=False)
    trainer, seen, resets, out = seeded_run(tiny_scene, tmp_path / "last", restarts, capsys)
    signature = trainer.pipeline.datamanager.selection_signature
    assert signature["after-add.restart-seeded-starts"] == "False" and signature["after-add"] == "restart-at-views 9"
    model = trainer.pipeline.model
    assert resets == [False, True]  # 3 -> 6: no; 6 -> 9: yes
    assert seen[29]["model_step"] == 29 and seen[30]["model_step"] == 0 and seen[39]["model_step"] == 9
    assert seen[30]["num_points"] == model.initial_gaussians["means"].shape[0] == 1500  # back to the seed points
    assert model.clock_scale == pytest.approx(10 / 40)  # every schedule squeezed into the 10 steps left


def test_a_seeded_run_restarts_at_twice_its_initial_views_by_default(tiny_scene, tmp_path, capsys):
    trainer, seen, resets, out = seeded_run(tiny_scene, tmp_path / "seeded", RestartsConfig(), capsys)
    model = trainer.pipeline.model
    assert "seed points: the splat restarts at 6 views from the capture's points" in out
    assert resets == [True, False]  # 3 -> 6: twice the initial views; 6 -> 9: no (12 never comes)
    assert seen[19]["model_step"] == 19 and seen[20]["model_step"] == 0 and seen[39]["model_step"] == 19
    assert seen[20]["num_points"] == model.initial_gaussians["means"].shape[0] == 1500  # back to the seed points
    assert model.clock_scale == pytest.approx(20 / 40)  # every schedule squeezed into the 20 steps left
    signature = trainer.pipeline.datamanager.selection_signature
    assert signature["after-add.restart-seeded-starts"] == "True" and signature["after-add"] == "off"


def resume(saved, now):
    from types import SimpleNamespace

    from hpgs_ns.trainer import check_resume_matches

    check_resume_matches(SimpleNamespace(datamanager=SimpleNamespace(loaded_selection_signature=saved,
                                                                     selection_signature=now)))


def test_a_checkpoint_from_before_seeded_restarts_were_the_default_resumes_as_it_was_trained():
    from hpgs_ns.trainer import CheckpointError

    base = {"selector": "random", "seed": "0", "seed-points": "colmap"}
    today = {**base, "after-add": "off", "after-add.restart-seeded-starts": "True"}
    # 0.4's checkpoint of a COLMAP start (never restarted): refused under today's default, naming the flag that
    # resumes it; with the flag it resumes
    old = {**base, "after-add": "off"}
    with pytest.raises(CheckpointError, match=r"after-add.restart-seeded-starts: checkpoint False, now True.*"
                                              r"--pipeline.model.restarts.seeded-starts False: seeded starts did not restart before"):
        resume(old, today)
    resume(old, {**today, "after-add.restart-seeded-starts": "False"})
    # 0.4's checkpoint that asked for it (then written inside after-add) resumes under today's default as it is
    resume({**base, "after-add": "restart-seeded-starts True, restart-at-views 8"},
           {**today, "after-add": "restart-at-views 8"})
    with pytest.raises(CheckpointError, match=r"after-add: checkpoint restart-at-views 8, now off.*"
                                              r"\(--pipeline.model.restarts.at-views 8\)"):
        resume({**base, "after-add": "restart-seeded-starts True, restart-at-views 8"}, today)
    # a random start has no such key, then or now: an old checkpoint of one resumes unchanged
    random_now = {**base, "seed-points": "colmap", "after-add": "off"}
    resume({**base, "after-add": "off"}, random_now)
    resume({**base, "after-add": "restart-seeded-starts True"}, random_now)


def test_a_checkpoint_of_the_old_default_selector_names_the_flag_that_resumes_it():
    from hpgs_ns.trainer import CheckpointError

    base = {"seed": "0", "seed-points": "colmap", "after-add": "off", "after-add.restart-seeded-starts": "True"}
    with pytest.raises(CheckpointError, match=r"selector: checkpoint hpgs, now farthest.*"
                                              r"--pipeline.selection.selector hpgs: the default was hpgs before farthest"):
        resume({**base, "selector": "hpgs", "hpgs.model": "shipped"}, {**base, "selector": "farthest"})
    with pytest.raises(CheckpointError, match=r"\(--pipeline.selection.selector fisher\)"):
        resume({**base, "selector": "fisher"}, {**base, "selector": "farthest"})
    resume({**base, "selector": "hpgs"}, {**base, "selector": "hpgs"})


@pytest.mark.parametrize("saved, flag", [
    ({"after-add": "refine-steps 1000"}, "--pipeline.selection.after-add.refine-steps 1000"),
    ({"after-add": "restart-at-views 8, error-points 500"}, "--pipeline.selection.after-add.error-points 500"),
    ({"late-view-boost": "3"}, "--pipeline.datamanager.late-view-boost 3"),
    ({"sh-degree-by-age": "True"}, "--pipeline.model.sh-degree-by-age True"),
    ({"near-cull": "0.15 0.25 support 2 to end"}, "--pipeline.model.near-cull-to-end True"),
])
def test_a_checkpoint_trained_with_a_removed_option_is_refused_naming_it_and_the_version(saved, flag):
    from hpgs_ns.trainer import CheckpointError

    base = {"selector": "random", "seed": "0", "seed-points": "colmap", "after-add": "off"}
    with pytest.raises(CheckpointError, match=rf"trained with {re.escape(flag)}, which hpgs-ns 0.5 removed; resume it "
                                              r"with hpgs-ns 0.4, the version that wrote it"):
        resume({**base, **saved}, base)
