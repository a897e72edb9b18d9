"""`--pipeline.model.sh-degree-by-age`: each Gaussian opens its SH degrees with its own age since a training
render first saw it (issue #46)."""

from __future__ import annotations

import torch
from conftest import model_trainer
from helpers import train_steps


def trainer_for(scene, out, by_age: bool):
    # degree l opens 2 l steps after a Gaussian is first seen
    return model_trainer(scene, out, sh_degree_interval=2, sh_degree_by_age=by_age)


def test_the_mask_opens_one_degree_per_interval_of_a_gaussians_age(tiny_scene, tmp_path):
    model = trainer_for(tiny_scene, tmp_path, by_age=True).pipeline.model
    n = model.num_points
    seen = torch.zeros(n, dtype=torch.long)
    seen[1], seen[2], seen[3] = 1, 4, 8  # first seen at steps 0, 3 and 7
    model.strategy_state[model.SEEN_AT] = seen
    model.step = 7  # ages 7, 4 and 0 -> degrees 3, 2 and 0 (interval 2, capped at sh-degree 3)
    mask = model.sh_age_mask()
    assert mask.shape == (n, 15)  # sh-degree 3: 15 coefficients besides the base colour
    assert mask[0].sum() == 0  # never seen: base colour only
    assert mask[1].sum() == 15
    assert torch.equal(mask[2], torch.tensor([1.0] * 8 + [0.0] * 7))  # degrees 1 (3 coefficients) and 2 (5)
    assert mask[3].sum() == 0
    model.config.sh_degree_by_age = False
    assert model.sh_age_mask() is None


def test_gaussians_added_late_keep_their_view_dependent_terms_closed_until_they_age(tiny_scene, tmp_path):
    rest = {}
    for by_age in (False, True):
        trainer = trainer_for(tiny_scene, tmp_path / str(by_age), by_age)
        model = trainer.pipeline.model
        train_steps(trainer, range(6))
        n = model.num_points
        if by_age:
            seen = model.seen_at()
            assert seen.shape == (n,) and int(seen.min()) >= 0 and int(seen.max()) <= 6
            assert (seen == 1).sum() > n // 2  # most of the splat is in view from step 0
        xyz = model.means.detach()[:5] + 0.001  # new Gaussians among visible ones, their SH bands zero
        model.add_gaussians(xyz, torch.full((5, 3), 128, dtype=torch.uint8), trainer.optimizers)
        train_steps(trainer, range(6, 8))
        rest[by_age] = model.gauss_params["features_rest"].detach().clone()
        if by_age:
            # the new rows were first seen at step 6 or 7 (or not yet): ages 0-1 < 2, so only their base colour trained
            new_seen = model.seen_at()[n:].tolist()
            assert set(new_seen) <= {0, 7, 8} and set(new_seen) & {7, 8}
            assert not rest[True][n:].any()
            # the old ones, seen from step 0, have degree 3 open, and it trained
            assert rest[True][:n][model.seen_at()[:n] == 1].abs().sum() > 0
    # without the option the global degree (3 at step 6) trains the new rows' terms at once
    assert rest[False][-5:].abs().sum() > 0


def test_ages_ride_through_densification_and_checkpoints(tiny_scene, tmp_path):
    from gsplat.strategy.ops import duplicate

    trainer = trainer_for(tiny_scene, tmp_path, by_age=True)
    model = trainer.pipeline.model
    train_steps(trainer, range(3))
    seen = model.seen_at().clone()
    pick = torch.zeros(model.num_points, dtype=torch.bool)
    pick[:4] = True
    duplicate(params=model.gauss_params, optimizers=trainer.optimizers.optimizers, state=model.strategy_state, mask=pick)
    assert torch.equal(model.seen_at(), torch.cat([seen, seen[:4]]))  # copies inherit their parent's age
    saved = model.get_extra_state()
    assert torch.equal(saved["strategy_state"][model.SEEN_AT], model.seen_at())
    fresh = trainer_for(tiny_scene, tmp_path / "fresh", by_age=True).pipeline.model
    fresh.set_extra_state(saved)
    assert torch.equal(fresh.strategy_state[model.SEEN_AT], model.seen_at())


def test_a_restart_forgets_the_ages_and_the_option_is_part_of_the_resume_signature(tiny_scene, tmp_path):
    trainer = trainer_for(tiny_scene, tmp_path, by_age=True)
    model = trainer.pipeline.model
    train_steps(trainer, range(3))
    assert model.seen_at().any()
    model.reset_to_initial(3, trainer.optimizers.optimizers)
    assert not model.seen_at().any() and model.seen_at().shape == (model.num_points,)  # all unseen again
    assert trainer.pipeline.datamanager.selection_signature["sh-degree-by-age"] == "True"
    off = trainer_for(tiny_scene, tmp_path / "off", by_age=False)
    assert "sh-degree-by-age" not in off.pipeline.datamanager.selection_signature
    assert model.SEEN_AT not in off.pipeline.model.strategy_state  # off: no ages are kept
