"""`--pipeline.datamanager.late-view-boost`: a view added late is drawn more often until it has had its share."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from conftest import run_training, short_config

from hpgs_ns.datamanager import ActiveDatamanager


def stub(active, boost, visits, seed=7):
    dm = SimpleNamespace(active=active, config=SimpleNamespace(late_view_boost=boost), visits=visits,
                         generator=torch.Generator().manual_seed(seed))
    dm.pass_views = lambda: ActiveDatamanager.pass_views(dm)
    return dm


def test_a_pass_holds_a_view_behind_the_mean_boost_times():
    behind = stub([0, 3, 5], 3, {0: 10, 3: 9, 5: 0})  # mean 6.33: view 5 is behind
    assert ActiveDatamanager.pass_views(behind) == [0, 3, 5, 5, 5]
    assert ActiveDatamanager.pass_views(stub([0, 3, 5], 3, {0: 4, 3: 4, 5: 4})) == [0, 3, 5]  # none behind
    assert ActiveDatamanager.pass_views(stub([0, 3, 5], 1, {0: 10, 3: 9, 5: 0})) == [0, 3, 5]  # off
    # a pass is a shuffle of those views
    assert sorted(ActiveDatamanager.sample_train_cameras(stub([0, 3, 5], 3, {0: 10, 3: 9, 5: 0}))) == [0, 3, 5, 5, 5]


def test_off_draws_the_same_passes_as_before():
    """Boost 1 shuffles the active views with the same generator calls as 0.4 did: the same training order."""
    order = torch.randperm(3, generator=torch.Generator().manual_seed(7)).tolist()
    assert ActiveDatamanager.sample_train_cameras(stub([0, 3, 5], 1, {5: 0})) == [[0, 3, 5][i] for i in order]


@pytest.mark.parametrize("boost", [1, 3])
def test_the_view_a_round_adds_catches_up_and_its_visits_survive_a_checkpoint(tiny_scene, tmp_path, boost):
    cfg = short_config(tiny_scene, tmp_path, steps=40, every=20, rounds=1, selector="random", late_view_boost=boost)
    trainer = run_training(cfg)
    dm = trainer.pipeline.datamanager
    added = dm.history[0].chosen_indices[0]
    others = [i for i in dm.active if i != added]
    assert sum(dm.visits.values()) == 40 and sorted(dm.visits) == sorted(dm.active)
    # 20 steps after the add: one view in 7 without the boost, about twice that with it (until it reaches the mean)
    if boost == 1:
        assert 2 <= dm.visits[added] <= 4
    else:
        assert dm.visits[added] >= 6 and dm.visits[added] >= min(dm.visits[i] for i in others)  # caught up
    state = dm.get_extra_state()
    dm.visits = {}
    dm.set_extra_state(state)
    assert sum(dm.visits.values()) == 40 and dm.visits[added] == state["visits"][str(added)]
    if boost != 1:
        assert trainer.pipeline.datamanager.selection_signature["late-view-boost"] == "3"


def test_draws_count_from_the_last_restart(tiny_scene, tmp_path):
    """A restart starts a fresh splat that has trained on no view: the shares late-view-boost evens out count from it."""
    from hpgs_ns.selection.after_add import AfterAddConfig

    cfg = short_config(tiny_scene, tmp_path, steps=40, every=20, rounds=1, selector="random", late_view_boost=3)
    cfg.pipeline.selection.after_add = AfterAddConfig(restart_at_views=(7,))  # the add at step 20 brings 6 -> 7 views
    trainer = run_training(cfg)
    dm = trainer.pipeline.datamanager
    assert dm.history[0].reset and len(dm.active) == 7
    # the 20 steps after the restart, not 40; every view starts level, so none is held back for long
    assert sum(dm.visits.values()) == 20 and max(dm.visits.values()) - min(dm.visits.get(i, 0) for i in dm.active) <= 4
