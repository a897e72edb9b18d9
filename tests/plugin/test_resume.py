"""`--load-dir` continues training: a run stopped after a densification step and resumed crosses further refines
and an opacity reset with the model's own tensors in its optimizers, picks the same views, and ends within 0.3 dB of
the uninterrupted run; checkpoints are never half-written; a resume that changes the selection is refused."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch
from conftest import run_training, short_config

from hpgs_ns.trainer import CheckpointError

TOTAL, STOP = 120, 56  # refines at 50, 60, 70, 80, 90; opacity reset at 100; rounds at 40 and 80


def resume_config(scene: Path, out: Path, steps: int = TOTAL, **options):
    """Densify every 10 steps from step 50 (35 training views + refine-every pause), reset opacities at 100."""
    cfg = short_config(scene, out, steps=TOTAL, every=40, rounds=2, **{"selector": "random", **options})
    if steps != TOTAL:
        # A run stopped early (a kill): its schedules are sized to TOTAL, as in the uninterrupted run.
        cfg.max_num_iterations, cfg.schedules_follow_steps = steps, False
    cfg.final_eval_json = out / "final_eval.json"
    model = cfg.pipeline.model
    model.refine_every, model.warmup_length, model.reset_alpha_every = 10, 20, 10
    return cfg


def same_tensors(trainer) -> bool:
    """Every optimizer steps the parameter the model trains (not a stale copy)."""
    groups = trainer.pipeline.get_param_groups()
    return all(opt.param_groups[0]["params"][0] is groups[name][0] for name, opt in trainer.optimizers.optimizers.items())


def adam_steps(trainer, name: str = "means") -> int:
    optimizer = trainer.optimizers.optimizers[name]
    return int(optimizer.state[optimizer.param_groups[0]["params"][0]]["step"])


@pytest.fixture(scope="module")
def runs(tiny_scene, tmp_path_factory):
    torch.manual_seed(0)
    whole = run_training(resume_config(tiny_scene, tmp_path_factory.mktemp("whole")))
    torch.manual_seed(0)
    first = run_training(resume_config(tiny_scene, tmp_path_factory.mktemp("first"), steps=STOP))
    first_dir = Path(first.base_dir)
    at_stop = {k: v.detach().clone() for k, v in first.pipeline.model.gauss_params.items()}
    copy = tmp_path_factory.mktemp("copy") / "run"
    shutil.copytree(first_dir, copy)
    cfg = resume_config(tiny_scene, tmp_path_factory.mktemp("resumed"))
    cfg.load_dir = copy / "nerfstudio_models"
    resumed = run_training(cfg)
    return {"whole": whole, "first": first, "resumed": resumed, "at_stop": at_stop, "copy": copy, "cfg": cfg}


def test_resumed_run_trains_with_the_models_own_tensors(runs):
    resumed, at_stop = runs["resumed"], runs["at_stop"]
    assert resumed.step == TOTAL - 1 and same_tensors(resumed)
    # Adam kept counting from the checkpoint (stock nerfstudio: stuck at STOP, the model never updated)
    assert adam_steps(resumed) == adam_steps(runs["whole"]) == TOTAL
    final = resumed.pipeline.model.gauss_params
    assert final["means"].shape != at_stop["means"].shape or not torch.equal(final["means"], at_stop["means"])
    assert not torch.equal(final["opacities"][: len(at_stop["opacities"])], at_stop["opacities"][: len(final["opacities"])])


def test_resumed_run_densified_and_reset_opacities_after_the_resume(runs):
    # At the opacity reset (step 100) every opacity is clamped to at most 2 x cull_alpha_thresh; 20 steps later
    # most are still far below their trained values, in both runs alike.
    for run in ("whole", "resumed"):
        model = runs[run].pipeline.model
        limit = torch.logit(torch.tensor(model.config.cull_alpha_thresh * 2.0)).item()
        assert float((model.gauss_params["opacities"] < limit + 1.0).float().mean()) > 0.9, run
    # refines ran after the resume: the count moved away from the checkpoint's
    assert runs["resumed"].pipeline.model.num_points != runs["at_stop"]["means"].shape[0]


def test_resumed_run_picks_the_same_views_and_matches_the_uninterrupted_psnr(runs):
    whole, resumed = runs["whole"].pipeline.datamanager, runs["resumed"].pipeline.datamanager
    assert [h.step for h in resumed.history] == [40, 80]
    assert [h.chosen for h in resumed.history] == [h.chosen for h in whole.history]
    psnr = [json.loads(Path(r.config.final_eval_json).read_text())["results"]["psnr"] for r in (runs["whole"], runs["resumed"])]
    assert abs(psnr[0] - psnr[1]) < 0.3, psnr
    # the resumed run's round log is final: both rounds, the last step's active set
    log = json.loads((Path(runs["resumed"].base_dir) / "selected_views.json").read_text())
    assert [r["step"] for r in log["rounds"]] == [40, 80] and len(log["active"]) == len(resumed.active) == 8


def test_a_truncated_latest_checkpoint_is_skipped_with_one_line(runs, tmp_path, capsys):
    folder = tmp_path / "nerfstudio_models"
    shutil.copytree(runs["copy"] / "nerfstudio_models", folder)
    latest = sorted(folder.glob("step-*.ckpt"))[-1]
    older = folder / "step-000000010.ckpt"
    shutil.copy(latest, older)  # a loadable older checkpoint (its content is step 55's; the name is what is picked)
    latest.write_bytes(latest.read_bytes()[:5000])  # a kill mid-save under stock nerfstudio
    cfg = resume_config(runs["cfg"].data, tmp_path / "out", steps=STOP + 1)
    cfg.load_dir = folder
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    out = capsys.readouterr().out
    assert f"skipping {latest.name}" in " ".join(out.split()) and "truncated" in out
    assert trainer._start_step == STOP  # step 55's content, loaded from the older name
    # the same file named with --load-checkpoint: one line, no resume
    cfg = resume_config(runs["cfg"].data, tmp_path / "out2", steps=STOP + 1)
    cfg.load_checkpoint = latest
    with pytest.raises(CheckpointError, match="does not load .* truncated"):
        cfg.setup(local_rank=0, world_size=1).setup()


def test_checkpoints_are_written_through_a_temp_file(runs, tmp_path, monkeypatch):
    trainer = runs["resumed"]
    saved = []
    real_save = torch.save
    monkeypatch.setattr(torch, "save", lambda obj, path: (saved.append(Path(path)), real_save(obj, path)))
    trainer.save_checkpoint(TOTAL - 1)
    assert saved and saved[0].name.startswith(".step-") and saved[0].parent == trainer.checkpoint_dir.parent
    assert not saved[0].exists() and (trainer.checkpoint_dir / f"step-{TOTAL - 1:09d}.ckpt").exists()
    assert not list(trainer.checkpoint_dir.parent.glob(".step-*"))


@pytest.mark.parametrize("option, value, named", [
    ("selector", "farthest", "selector: checkpoint random, now farthest"),
    ("seed", 3, "seed: checkpoint 0, now 3"),
    ("select_every", 30, "select-every: checkpoint 40, now 30"),
])
def test_a_resume_that_changes_the_selection_is_refused(runs, tmp_path, option, value, named):
    cfg = resume_config(runs["cfg"].data, tmp_path / "out", **{option: value})
    cfg.load_dir = runs["copy"] / "nerfstudio_models"
    with pytest.raises(CheckpointError, match=named):
        cfg.setup(local_rank=0, world_size=1).setup()


def test_a_resume_that_extends_a_run_follows_the_longer_schedule_and_counts_its_rounds(tiny_scene, tmp_path, capsys):
    """`--load-dir` of a finished 20-step run with `--max-num-iterations 40`: the checkpoint's schedules (sized to
    20 steps) are re-sized to 40, so from the loaded step on every learning rate is the uninterrupted 40-step run's
    (not the 20-step schedule's floor), and the start-up line counts the round run before the checkpoint."""
    from conftest import run_training_seeing

    def config(steps: int, out: Path):
        return short_config(tiny_scene, out, steps=steps, every=10, rounds=7, selector="random")

    rates = lambda trainer, step: {k: o.param_groups[0]["lr"] for k, o in trainer.optimizers.optimizers.items()}  # noqa: E731
    torch.manual_seed(0)
    whole, whole_rates = run_training_seeing(config(40, tmp_path / "whole"), rates)
    torch.manual_seed(0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = run_training(config(20, tmp_path / "first"))
    # the warnings the plugin's own training code set off on a CPU are gone (nerfstudio's GradScaler, its writer's
    # float() of a loss that requires grad): fixed where they come from, nothing filtered
    said = [str(w.message) for w in caught]
    assert not [m for m in said if "GradScaler" in m or "requires_grad=True to a scalar" in m], said
    capsys.readouterr()
    cfg = config(40, tmp_path / "longer")
    cfg.load_dir = Path(first.base_dir) / "nerfstudio_models"
    longer, longer_rates = run_training_seeing(cfg, rates)
    out = " ".join(capsys.readouterr().out.split())
    assert min(longer_rates) == 20 and sorted(longer_rates) == list(range(20, 40))
    for step in range(20, 40):
        assert longer_rates[step] == pytest.approx(whole_rates[step], rel=1e-9), step
    floor = whole.config.optimizers["means"]["scheduler"].lr_final
    assert longer_rates[30]["means"] > 3 * floor  # the 20-step schedule would hold it at its floor
    assert "the learning-rate schedules now end at step 40 (the checkpoint's ended at step 20)" in out
    assert "only 3 of 7 selection rounds will run (1 before the checkpoint, 2 from step 20)" in out
    assert [h.step for h in longer.pipeline.datamanager.history] == [h.step for h in whole.pipeline.datamanager.history] == [10, 20, 30]
    # the re-sized schedule is saved: a resume of the extended run keeps it
    state = torch.load(sorted((Path(longer.base_dir) / "nerfstudio_models").glob("*.ckpt"))[-1], map_location="cpu")
    assert state["schedulers"]["means"]["lr_lambdas"][0]["max_steps"] == 40


def test_a_fisher_checkpoint_from_before_the_criterion_resumes_under_trace_only():
    from types import SimpleNamespace

    from hpgs_ns.selection.config import SelectionConfig
    from hpgs_ns.trainer import CheckpointError, check_resume_matches

    now = SelectionConfig(selector="fisher").resume_signature(0)
    written_before = {k: v for k, v in now.items() if k != "fisher.criterion"}

    def pipeline(signature):
        return SimpleNamespace(datamanager=SimpleNamespace(loaded_selection_signature=written_before,
                                                           selection_signature=signature))

    check_resume_matches(pipeline(now))  # trace, as such checkpoints trained
    with pytest.raises(CheckpointError) as err:
        check_resume_matches(pipeline(SelectionConfig(selector="fisher", fisher=type(SelectionConfig().fisher)(
            criterion="dopt")).resume_signature(0)))
    assert "fisher.criterion: checkpoint trace, now dopt" in str(err.value)


def test_a_resume_with_another_selector_names_the_selector_not_its_options():
    from types import SimpleNamespace

    from hpgs_ns.trainer import CheckpointError, check_resume_matches

    saved = {"selector": "farthest", "farthest.tie-tolerance": "0.001", "seed": "0"}
    now = {"selector": "random", "seed": "0"}
    with pytest.raises(CheckpointError) as err:
        check_resume_matches(SimpleNamespace(datamanager=SimpleNamespace(loaded_selection_signature=saved,
                                                                         selection_signature=now)))
    assert "(selector: checkpoint farthest, now random)" in str(err.value) and "tie-tolerance" not in str(err.value)
