"""`--pipeline.model.means-lr-by-age`: each Gaussian's position learning rate runs the means' decay from the step a
training render first saw it (issue #46)."""

from __future__ import annotations

import pytest
import torch
from conftest import model_trainer, short_config
from helpers import train_steps

from hpgs_ns.schedules import DecayMultiplier

SPLATFACTO_MEANS = dict(lr_init=1.6e-4, lr_final=1.6e-6, lr_pre_warmup=1e-8, warmup_steps=0)


@pytest.mark.parametrize("warmup_steps, cosine", [(0, False), (30, False), (30, True)])
def test_the_decay_at_many_fractions_is_the_schedule_at_those_steps(warmup_steps, cosine):
    multiplier = DecayMultiplier(lr_init=1e-2, lr_final=1e-4, lr_pre_warmup=1e-8, warmup_steps=warmup_steps,
                                 max_steps=200, cosine=cosine)
    steps = [0, 1, 15, 29, 30, 31, 100, 199, 200, 250]
    got = multiplier.at_fraction(torch.tensor([s / 200 for s in steps], dtype=torch.float64))
    assert got.tolist() == pytest.approx([multiplier(s) for s in steps], rel=1e-12)
    assert float(multiplier.at_fraction(torch.tensor([1.0]))) == pytest.approx(1e-2)  # lr_final / lr_init


def model_stub(seen_at, step):
    """What means_lr_ratio reads of a model: its ages, its step and its means' dtype."""
    from hpgs_ns.model import HpgsSplatfactoModel

    stub = type("Stub", (), {})()
    stub.SEEN_AT = HpgsSplatfactoModel.SEEN_AT
    stub.strategy_state = {HpgsSplatfactoModel.SEEN_AT: torch.tensor(seen_at)}
    stub.num_points = len(seen_at)
    stub.step = step
    stub.means = torch.zeros(len(seen_at), 3)
    stub.seen_at = HpgsSplatfactoModel.seen_at.__get__(stub)
    return stub


def ratios(seen_at, step, speed=1.0, max_steps=100):
    from hpgs_ns.model import HpgsSplatfactoModel

    multiplier = DecayMultiplier(max_steps=max_steps, speed=speed, **SPLATFACTO_MEANS)
    return HpgsSplatfactoModel.means_lr_ratio(model_stub(seen_at, step), multiplier).tolist()


def test_a_gaussian_first_seen_late_gets_the_start_rate_then_decays_to_the_same_floor():
    # seen_at: never seen, seen at step 0, first seen at step 50 (ages are 1 + the step)
    at_50 = ratios([0, 1, 51], step=50)
    assert at_50[:2] == [1.0, 1.0]
    assert at_50[2] == pytest.approx(10.0, rel=1e-6)  # its own rate 1.6e-4 against the shared 100^-0.5 of it
    at_75 = ratios([0, 1, 51], step=75)
    assert at_75[2] == pytest.approx(100 ** (0.75 - 0.5), rel=1e-6)  # halfway down its own decay at 3/4 of the run's
    assert ratios([0, 1, 51], step=100)[2] == pytest.approx(1.0)  # everyone ends at the final rate


def test_after_a_restart_ages_and_the_squeezed_decay_count_from_it():
    # restart_schedules(span=50) sets speed 2: the decay spans the 50 model steps left; a Gaussian first seen 25
    # steps after the restart starts its own decay there
    got = ratios([1, 26], step=25, speed=2.0)
    assert got[0] == 1.0
    assert got[1] == pytest.approx(10.0, rel=1e-6)


def trainer_for(scene, out, by_age: bool):
    return model_trainer(scene, out, means_lr_by_age=by_age)


def test_gaussians_added_late_move_faster_than_under_the_shared_rate(tiny_scene, tmp_path):
    moved, kept = {}, {}
    for by_age in (False, True):
        torch.manual_seed(0)
        trainer = trainer_for(tiny_scene, tmp_path / str(by_age), by_age)
        model = trainer.pipeline.model
        train_steps(trainer, range(8))
        n = model.num_points
        xyz = model.means.detach()[:16] + 0.01  # new Gaussians among visible ones
        model.add_gaussians(xyz, torch.full((16, 3), 128, dtype=torch.uint8), trainer.optimizers)
        start = model.means.detach().clone()
        train_steps(trainer, range(8, 11))
        step = (model.means.detach() - start).norm(dim=-1)
        moved[by_age], kept[by_age] = step[n:], step[:n]
        if by_age:
            assert model.seen_at()[n:].max() >= 9  # the new rows were first seen after the add
            assert model.means_before_step is None  # consumed by the step it was taken for
    seen = moved[True] > 0
    assert seen.any()
    # at steps 8-10 of 12 the shared rate is 100^(-8/12) .. 100^(-10/12) of the start: new rows move ~10-20x more
    gain = float(moved[True][seen].median() / moved[False][seen].median())
    assert gain > 5
    # the Gaussians seen from step 0 keep the shared schedule (their paths differ only through the renders)
    assert float(kept[True].median()) == pytest.approx(float(kept[False].median()), rel=0.5)


def test_the_option_records_ages_and_is_part_of_the_resume_signature(tiny_scene, tmp_path):
    trainer = trainer_for(tiny_scene, tmp_path, by_age=True)
    model = trainer.pipeline.model
    train_steps(trainer, range(2))
    assert model.seen_at().any()
    assert trainer.pipeline.datamanager.selection_signature["means-lr-by-age"] == "True"
    off = trainer_for(tiny_scene, tmp_path / "off", by_age=False)
    train_steps(off, range(2))
    assert "means-lr-by-age" not in off.pipeline.datamanager.selection_signature
    assert off.pipeline.model.SEEN_AT not in off.pipeline.model.strategy_state  # off: no ages, no snapshots
    assert off.pipeline.model.means_before_step is None


def test_without_the_hpgs_decay_the_option_says_at_start_that_it_does_nothing(tiny_scene, tmp_path, capsys):
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    cfg = short_config(tiny_scene, tmp_path, steps=4, rounds=0)
    cfg.pipeline.model.means_lr_by_age = True
    cfg.optimizers["means"]["scheduler"] = ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=4)  # stock
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    train_steps(trainer, range(2))
    out = capsys.readouterr().out
    assert out.count("means-lr-by-age does nothing in this run") == 1
    assert trainer.pipeline.model.means_decay() is None
