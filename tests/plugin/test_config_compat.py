"""Runs saved by hpgs-ns 0.1 and 0.2 still open: `ns-eval`/`ns-viewer` (nerfstudio's `eval_setup`) and `--load-config`.

tests/data/run-0.1.0 and run-0.2.0 hold the config.yml, checkpoint and round log of a 30-step CPU `farthest` run on
the 24-camera synthetic ring (4-6 initial views, rounds at steps 10 and 20). 0.1 saved a VanillaPipeline with the
rounds inside the datamanager and bare file names; 0.2 the hpgs pipeline with the selection options on the
datamanager (`--pipeline.datamanager.selector`); 0.3 moved them to `--pipeline.selection`. The checkpoints were saved
without splatfacto's LPIPS weights (10 MB, rebuilt at load).
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import pytest
import yaml

DATA = Path(__file__).resolve().parents[1] / "data"  # tests/data
VERSIONS = ("0.1.0", "0.2.0")


@pytest.fixture(scope="module", params=VERSIONS)
def old_run(request, tmp_path_factory) -> Path:
    """A saved run, its config pointed at a fresh copy of the synthetic scene it was trained on."""
    from hpgs_ns.scenes.synthetic import make_scene

    root = tmp_path_factory.mktemp(f"run-{request.param}")
    scene = make_scene(root / "scene", layout="ring", num_cameras=24, width=32, height=24, num_points=300, seed=0)
    run = root / "runs" / "test" / "hpgs" / "run"
    shutil.copytree(DATA / f"run-{request.param}", run)
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    config.data = config.pipeline.datamanager.data = scene
    config.output_dir = root / "runs"
    config.final_eval_json = None
    (run / "config.yml").write_text(yaml.dump(config))
    return run


def test_an_old_config_reads_its_selection_options_into_the_new_place(old_run):
    from hpgs_ns.compat import upgrade_pipeline_config
    from hpgs_ns.pipeline import HpgsPipelineConfig

    config = yaml.load((old_run / "config.yml").read_text(), Loader=yaml.Loader)
    upgrade_pipeline_config(config, HpgsPipelineConfig)  # 0.1: a VanillaPipeline
    selection = config.pipeline.selection
    assert (selection.selector, selection.select_every, selection.max_rounds) == ("farthest", 10, 2)
    assert "selector" not in vars(config.pipeline.datamanager)  # one place for each option once read


def test_ns_eval_and_ns_viewer_load_an_old_run(old_run):
    """`ns-eval` and `ns-viewer` both load a run through nerfstudio's `eval_setup`."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, checkpoint, step = eval_setup(old_run / "config.yml", test_mode="test")
    assert step == 29 and checkpoint.name == "step-000000029.ckpt"
    dm = pipeline.datamanager
    # Both versions picked the same views; 0.1 saved bare file names, the views are named by their path below the
    # data root now.
    assert [dm.image_names[i] for i in dm.active] == [f"images/{n:04d}.png" for n in (1, 4, 9, 13, 15, 23)]
    assert [(h.step, h.chosen) for h in dm.history] == [(10, ["images/0004.png"]), (20, ["images/0013.png"])]
    # The renders ns-eval scores (its LPIPS needs larger images than these 32x24 ones).
    from hpgs_ns.metrics import psnr

    camera, batch = next(iter(dm.fixed_indices_eval_dataloader))
    rgb = pipeline.model.get_outputs_for_camera(camera)["rgb"]
    value = psnr(rgb.clamp(0, 1).cpu(), batch["image"].float().div(255)[..., :3].cpu())
    assert math.isfinite(value) and value > 10


def test_resuming_an_old_run_upgrades_its_pipeline_and_keeps_selecting(old_run):
    from hpgs_ns.pipeline import HpgsPipeline

    config = yaml.load((old_run / "config.yml").read_text(), Loader=yaml.Loader)
    config.load_dir = old_run / "nerfstudio_models"
    config.max_num_iterations = 42
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    assert isinstance(trainer.pipeline, HpgsPipeline)
    trainer.pipeline.rounds.config.max_rounds = 3  # a longer run than the saved one
    trainer.train()
    log = json.loads((old_run / "selected_views.json").read_text())
    assert [r["step"] for r in log["rounds"]] == [10, 20, 30]
    assert len(log["active"]) == 7


def test_a_0_4_model_config_reads_its_floater_guard_options_into_the_strategy_group():
    from hpgs_ns.model import HpgsSplatfactoModelConfig

    text = yaml.dump(HpgsSplatfactoModelConfig())
    assert "near_cull:" in text
    # 0.4 wrote the guard's options as three model fields, and no strategy group
    old = text.replace("near_cull: !!python/object:hpgs_ns.strategies.near_cull.NearCullConfig", "near_cull_old:")
    old += "near_cull_screen: 0.1\nnear_cull_depth: 0.3\nnear_cull_support: 1\n"
    config = yaml.load(old, Loader=yaml.UnsafeLoader)
    assert (config.near_cull.screen, config.near_cull.depth, config.near_cull.support) == (0.1, 0.3, 1)
    assert "near_cull_screen" not in config.__dict__


def test_a_0_4_checkpoint_keeps_the_guards_count():
    from hpgs_ns import compat

    assert compat.strategy_states({"near_culled": 5}) == {"near-cull": {"culled": 5}}
    assert compat.strategy_states({"strategies": {"near-cull": {"culled": 2}}}) == {"near-cull": {"culled": 2}}


def test_a_strict_init_config_yml_reads_as_colmap_initial():
    from hpgs_ns.datamanager import ActiveDatamanagerConfig

    text = yaml.dump(ActiveDatamanagerConfig()) + "strict_init: true\n"
    config = yaml.load(text, Loader=yaml.UnsafeLoader)
    assert config.seed_points == "colmap-initial" and "strict_init" not in config.__dict__
    assert yaml.load(yaml.dump(ActiveDatamanagerConfig()) + "strict_init: false\n", Loader=yaml.UnsafeLoader).seed_points == "auto"


def test_a_checkpoints_view_names_map_to_the_splits_names_now():
    from hpgs_ns.compat import view_names_now

    names = ["images/a.png", "images/b.png"]
    assert view_names_now(names, names) == {}
    assert view_names_now(["a.png", "b.png"], names) == {"a.png": "images/a.png", "b.png": "images/b.png"}  # 0.1's
    assert view_names_now(["a.png", "c.png"], names) is None and view_names_now(None, names) is None


def test_a_0_4_config_yml_reads_its_restart_options_into_the_models_restarts_group():
    from hpgs_ns.method_config import hpgs_trainer_config

    text = yaml.dump(hpgs_trainer_config().pipeline)
    assert "  restarts: !!python/object:hpgs_ns.strategies.restarts.RestartsConfig\n" in text
    # 0.4 wrote them on the selection, in a class of their own (gone now), beside fields 0.5 removed
    old_model = re.sub(r"  restarts: !!python/object:hpgs_ns.strategies.restarts.RestartsConfig\n(    .*\n)+", "", text)
    assert "restarts" not in old_model.split("selection:")[0]
    old = old_model.replace("selection: !!python/object:hpgs_ns.selection.config.SelectionConfig\n",
                            "selection: !!python/object:hpgs_ns.selection.config.SelectionConfig\n"
                            "  after_add: !!python/object:hpgs_ns.selection.after_add.AfterAddConfig\n"
                            "    restart_at_views: !!python/tuple\n    - 8\n    - 16\n"
                            "    restart_random_starts: false\n    restart_seeded_starts: false\n    refine_steps: 0\n"
                            "  reset_after_add: true\n")
    for loader in (yaml.Loader, yaml.UnsafeLoader):  # nerfstudio's eval_setup and --load-config read with Loader
        config = yaml.load(old, Loader=loader)
        restarts = config.model.restarts
        assert (restarts.at_views, restarts.random_starts, restarts.active_starts, restarts.seeded_starts,
                restarts.every_round) == ((8, 16), False, True, False, True)
        assert "after_add" not in config.selection.__dict__ and "reset_after_add" not in config.selection.__dict__
    # a config.yml of 0.5 reads its own group as written
    assert yaml.load(text, Loader=yaml.Loader).model.restarts == hpgs_trainer_config().pipeline.model.restarts
