"""Shared fixtures: a tiny synthetic scene, a short in-process `hpgs` training run, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def shared_dir() -> Path:
    """`../shared` beside the checkout, or $HPGS_SHARED."""
    return Path(os.environ.get("HPGS_SHARED", REPO.parent / "shared"))


def require_shared(*parts: str) -> Path:
    path = shared_dir().joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data {path} not found (set HPGS_SHARED to the shared/ folder)")
    return path


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 40-camera, 64x48 synthetic `ring` scene (35 training views, 5 test views)."""
    from hpgs_ns.scenes.synthetic import make_scene

    return make_scene(tmp_path_factory.mktemp("scenes") / "ring", layout="ring", num_cameras=40, width=64, height=48, num_points=1500, seed=0)


def short_config(scene: Path, out: Path, steps: int = 60, every: int = 20, rounds: int = 2, initial: int = 6, **dm):
    """An `hpgs` trainer config scaled down for tests (CPU rasterizer, tensorboard, no viewer)."""
    from hpgs_ns.method_config import hpgs_trainer_config

    cfg = hpgs_trainer_config(steps)
    cfg.data = scene
    cfg.pipeline.datamanager.data = scene
    cfg.output_dir = out
    cfg.experiment_name = "test"
    cfg.timestamp = "run"
    cfg.vis = "tensorboard"
    cfg.steps_per_save = steps
    cfg.steps_per_eval_image = 10 * steps
    cfg.steps_per_eval_all_images = 10 * steps
    cfg.logging.local_writer.enable = False
    cfg.pipeline.model.rasterizer = "cpu"
    cfg.pipeline.model.warmup_length = 20
    cfg.pipeline.model.refine_every = 20
    cfg.pipeline.model.num_downscales = 0  # full resolution from the start: short runs visibly improve
    cfg.pipeline.model.sh_degree_interval = 20
    d = cfg.pipeline.datamanager
    d.num_initial_views, d.select_every, d.max_rounds = initial, every, rounds
    for key, value in dm.items():
        setattr(d, key, value)
    return cfg


def run_training(cfg):
    """Set up and train in-process, the way `ns-train` does; returns the trainer."""
    cfg.set_timestamp()
    cfg.save_config()
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    return trainer
