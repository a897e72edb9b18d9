"""Splatfacto's pose refinement (`--pipeline.model.camera-optimizer.mode SO3xR3`) under the active datamanager:
per-view corrections are indexed by the full training pool, so only views trained on may move."""

from __future__ import annotations

import torch
from conftest import run_training, short_config


def test_pose_refinement_moves_only_the_views_trained_on(tiny_scene, tmp_path):
    cfg = short_config(tiny_scene, tmp_path, steps=40, every=20, rounds=1)
    cfg.pipeline.model.camera_optimizer.mode = "SO3xR3"
    trainer = run_training(cfg)
    dm, model = trainer.pipeline.datamanager, trainer.pipeline.model

    adjustment = model.camera_optimizer.pose_adjustment.detach()
    assert adjustment.shape == (len(dm.image_names), 6)
    moved = set(torch.nonzero(adjustment.abs().sum(dim=1) > 0).flatten().tolist())
    initial = set(dm.active) - {int(i) for r in dm.history for i in r.chosen_indices}
    assert initial <= moved, "an initial view was trained on for 40 steps but its pose never moved"
    assert moved <= set(dm.active), f"withheld views {sorted(moved - set(dm.active))} moved"
    assert torch.isfinite(adjustment).all()
