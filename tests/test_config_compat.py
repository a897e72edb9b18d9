"""A run saved by hpgs-ns 0.1 (tests/data/run-0.1.0: config.yml, checkpoint, round log of a 30-step CPU run on the
24-camera synthetic ring) still opens after the 0.2 layout change: its config names classes by their 0.1 module
paths and a VanillaPipeline. The checkpoint was saved without splatfacto's LPIPS weights (10 MB, rebuilt at load)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import yaml

OLD_RUN = Path(__file__).resolve().parent / "data" / "run-0.1.0"


@pytest.fixture(scope="module")
def old_run(tmp_path_factory) -> Path:
    """The saved run, its config pointed at a fresh copy of the synthetic scene it was trained on."""
    from hpgs_ns.scenes.synthetic import make_scene

    root = tmp_path_factory.mktemp("old")
    scene = make_scene(root / "scene", layout="ring", num_cameras=24, width=32, height=24, num_points=300, seed=0)
    run = root / "runs" / "test" / "hpgs" / "run"
    shutil.copytree(OLD_RUN, run)
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    config.data = config.pipeline.datamanager.data = scene
    config.output_dir = root / "runs"
    config.final_eval_json = None
    (run / "config.yml").write_text(yaml.dump(config))
    return run


def test_old_config_names_old_module_paths():
    text = (OLD_RUN / "config.yml").read_text()
    assert "nerfstudio.pipelines.base_pipeline.VanillaPipelineConfig" in text
    assert "hpgs_ns.trainer.FloatExponentialDecaySchedulerConfig" in text


def test_ns_eval_and_ns_viewer_load_an_old_run(old_run):
    """`ns-eval` and `ns-viewer` both load a run through nerfstudio's `eval_setup`."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, checkpoint, step = eval_setup(old_run / "config.yml", test_mode="test")
    assert step == 29 and checkpoint.name == "step-000000029.ckpt"
    saved = json.loads((old_run / "selected_views.json").read_text())
    dm = pipeline.datamanager
    # 0.1 saved bare file names; the views are named by their path below the data root now
    assert [dm.image_names[i] for i in dm.active] == [f"images/{n}" for n in saved["active"]]
    assert [h["chosen"] for h in dm.history] == [[f"images/{n}" for n in r["chosen"]] for r in saved["rounds"]]
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
    config.pipeline.datamanager.max_rounds = 3
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    assert isinstance(trainer.pipeline, HpgsPipeline)
    trainer.train()
    log = json.loads((old_run / "selected_views.json").read_text())
    assert [r["step"] for r in log["rounds"]] == [10, 20, 30]
    assert len(log["active"]) == 7
