"""Any nerfstudio scene: `ns-train hpgs` takes nerfstudio's dataparsers as a subcommand (Mip-NeRF 360 COLMAP by
default), names views by their path relative to the data root, keeps test views out whatever the parser, and
says in one line what is wrong with a scene or why fewer rounds than asked will run."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import require_shared, run_training, short_config, stock_ns_viewer_page
from PIL import Image

from hpgs_ns.datamanager import ActiveViewError
from hpgs_ns.dataparser import (
    HpgsNerfstudioDataParserConfig,
    MipNerf360DataParserConfig,
    SceneDataError,
    read_ply_points,
    scene_dataparser,
    view_name,
)
from hpgs_ns.selection.config import SelectionConfig
from hpgs_ns.selection.rounds import SelectionRounds

ENV = {k: v for k, v in os.environ.items() if k != "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD"}


@pytest.fixture(scope="module")
def fox(tmp_path_factory) -> Path:
    """instant-ngp's fox (nerfstudio-data, 67 photos) with an images_4/ folder (135x240), so the CPU can train it."""
    source = require_shared("data", "fox-nerfstudio")
    fox = tmp_path_factory.mktemp("fox") / "fox"
    (fox / "images_4").mkdir(parents=True)
    shutil.copy(source / "transforms.json", fox / "transforms.json")
    for path in sorted((source / "images").iterdir()):
        with Image.open(path) as im:
            im.resize((im.width // 4, im.height // 4), Image.Resampling.BICUBIC).save(fox / "images_4" / path.name, quality=95)
    return fox


def ns_train(out: Path, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "nerfstudio.scripts.train", "hpgs", "--output-dir", str(out), "--experiment-name", "x",
           "--timestamp", "run", "--vis", "tensorboard", "--pipeline.model.rasterizer", "cpu", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=ENV)


def test_ns_train_hpgs_on_a_nerfstudio_data_capture_then_stock_ns_eval_and_ns_viewer(fox, tmp_path):
    proc = ns_train(
        tmp_path, "--max-num-iterations", "40", "--steps-per-save", "40", "--steps-per-eval-all-images", "400",
        "--steps-per-eval-image", "400", "--pipeline.datamanager.num-initial-views", "6",
        "--pipeline.selection.select-every", "15", "--pipeline.selection.max-rounds", "2",
        "--pipeline.selection.selector", "farthest", "--pipeline.model.num-random", "3000",
        "--pipeline.model.num-downscales", "0", "nerfstudio-data", "--data", str(fox), "--downscale-factor", "4",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    # no point cloud: `seed-points auto` triangulates the active views (or falls back to random points, saying so)
    out = " ".join(proc.stdout.split())
    assert "seed points: the capture has no point cloud, so they are triangulated from the active views" in out
    assert "starts from random points" not in out or "Seed points: only" in out
    run = tmp_path / "x" / "hpgs" / "run"
    log = json.loads((run / "selected_views.json").read_text())
    assert [r["step"] for r in log["rounds"]] == [15, 30]
    # nerfstudio-data's own split: --eval-mode fraction, 90% for training -> 6 of 67 test views
    names = [f"images/{p.name}" for p in sorted((fox / "images_4").iterdir())]
    assert len(log["test"]) == 6 and set(log["test"]) < set(names)
    assert sorted(log["active"] + log["withheld"] + log["test"]) == names
    assert len(log["active"]) == 8 and not set(log["test"]) & set(log["active"] + log["withheld"])

    config = run / "config.yml"
    out = tmp_path / "eval.json"
    subprocess.run([sys.executable, "-m", "nerfstudio.scripts.eval", "--load-config", str(config), "--output-path", str(out)],
                   check=True, env=ENV, capture_output=True, timeout=600)
    assert 5 < json.loads(out.read_text())["results"]["psnr"] < 60
    stock_ns_viewer_page(config, ENV)


def test_old_dataparser_spelling_fails_at_parse_naming_the_subcommands(capsys):
    """0.1 set dataparser options as `--pipeline.datamanager.dataparser.X`; tyro's parse error names the dataparser
    subcommands they now follow (nothing checks the command line at import any more)."""
    import tyro

    from hpgs_ns.method_config import hpgs_trainer_config

    default = hpgs_trainer_config(100)
    with pytest.raises(SystemExit) as exit_info:
        tyro.cli(type(default), default=default, args=["--data", "s", "--pipeline.datamanager.dataparser.downscale-factor", "4"])
    assert exit_info.value.code == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "--pipeline.datamanager.dataparser.downscale-factor" in err and "mipnerf360, nerfstudio-data" in err


def test_a_capture_folder_given_to_the_default_parser_names_the_subcommand(fox):
    with pytest.raises(
        SceneDataError, match=f"{fox} is a nerfstudio-data folder .*run: ns-train hpgs \\[options\\] nerfstudio-data --data {fox}"
    ):
        MipNerf360DataParserConfig(data=fox).setup().get_dataparser_outputs("train")
    assert scene_dataparser(fox) == "nerfstudio-data"


def test_views_are_named_by_their_path_below_the_data_root():
    assert view_name(Path("/d/train/r_0.png"), Path("/d")) == "train/r_0.png"
    assert view_name(Path("/d/test/r_0.png"), Path("/d")) == "test/r_0.png"
    assert view_name(Path("/d/images_4/0001.jpg"), Path("/d")) == "images/0001.jpg"  # one name at every resolution


def test_seed_points_come_from_the_capture_ply_without_open3d(fox, tmp_path, monkeypatch):
    import numpy as np
    from plyfile import PlyData, PlyElement

    monkeypatch.setitem(sys.modules, "open3d", None)  # importing it would fail
    scene = tmp_path / "fox"
    shutil.copytree(fox, scene)
    points = np.array([(0.1, 0.2, 0.3, 255, 0, 0), (-1.0, 0.5, 2.0, 0, 128, 255)],
                      dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    PlyData([PlyElement.describe(points, "vertex")]).write(str(scene / "sparse_pc.ply"))
    xyz, rgb = read_ply_points(scene / "sparse_pc.ply")
    assert xyz.shape == (2, 3) and rgb.tolist() == [[255, 0, 0], [0, 128, 255]]
    outputs = HpgsNerfstudioDataParserConfig(data=scene, downscale_factor=4).setup().get_dataparser_outputs("train")
    meta = outputs.metadata
    expected = (np.c_[points[["x", "y", "z"]].tolist(), np.ones(2)] @ outputs.dataparser_transform.numpy().T) * outputs.dataparser_scale
    assert np.allclose(meta["points3D_xyz"].numpy(), expected, atol=1e-5)
    assert meta["points3D_rgb"].tolist() == [[255, 0, 0], [0, 128, 255]]


def test_an_explicit_downscale_factor_writes_images_n_and_a_mismatched_one_names_the_rounding(tmp_path):
    from hpgs_ns.scenes.synthetic import make_scene

    scene = make_scene(tmp_path / "odd", layout="ring", num_cameras=16, width=67, height=51, num_points=300, seed=0)
    outputs = MipNerf360DataParserConfig(data=scene, downscale_factor=4).setup().get_dataparser_outputs("train")
    assert (scene / "images_4").is_dir() and int(outputs.cameras.width[0]) == 16  # floor(67 / 4)
    with Image.open(outputs.image_filenames[0]) as im:
        assert im.size == (16, 12)
    # an images_4 made by rounding (17x13) where the cameras floor (16x12)
    for path in (scene / "images").iterdir():
        with Image.open(path) as im:
            im.resize((17, 13)).save(scene / "images_4" / path.name)
    with pytest.raises(SceneDataError, match=r"is 17x13 but its camera says 16x12 .*; pass mipnerf360 --downscale-rounding-mode round$"):
        MipNerf360DataParserConfig(data=scene, downscale_factor=4).setup().get_dataparser_outputs("train")


def test_splits_without_test_views_or_overlapping_are_one_line_errors(fox, tiny_scene, tmp_path):
    cfg = short_config(tiny_scene, tmp_path / "all", steps=4)
    cfg.pipeline.datamanager.dataparser.eval_mode = "all"
    with pytest.raises(ActiveViewError, match="--eval-mode all trains on the test views too"):
        run_training(cfg)
    scene = tmp_path / "fox"
    shutil.copytree(fox, scene)
    meta = json.loads((scene / "transforms.json").read_text())
    files = [f["file_path"] for f in meta["frames"]]
    meta["train_filenames"], meta["val_filenames"], meta["test_filenames"] = files[:60], files[55:], files[55:]
    (scene / "transforms.json").write_text(json.dumps(meta))
    cfg = short_config(scene, tmp_path / "overlap", steps=4)
    cfg.pipeline.datamanager.dataparser = HpgsNerfstudioDataParserConfig(data=scene, downscale_factor=4)
    with pytest.raises(ActiveViewError, match=r"5 test views are also training views \(e.g. images/"):
        run_training(cfg)


@pytest.mark.parametrize("mode", ["active", "auto", "colmap"])
def test_seed_points_on_a_capture_without_a_ply_say_only_what_they_do(fox, tmp_path, capsys, mode):
    cfg = short_config(fox, tmp_path, steps=1, rounds=0, initial=8, seed_points=mode)
    cfg.pipeline.datamanager.dataparser = HpgsNerfstudioDataParserConfig(data=fox, downscale_factor=4)
    cfg.pipeline.model.num_random = 3000
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    assert cfg.pipeline.datamanager.dataparser.load_3D_points is True  # skipped for this setup only, not changed
    out = capsys.readouterr()
    lines = [line for line in (out.out + out.err).splitlines() if "seed points" in line.lower() or "random points" in line]
    num_points = trainer.pipeline.model.num_points
    if mode == "colmap":  # the old default: splatfacto's random start, said once
        assert len(lines) == 1 and "so the splat starts from random points" in lines[0], lines
        assert num_points == 3000
        return
    # what was triangulated (auto: after one line saying why); nothing says "random start"
    assert len(lines) == (2 if mode == "auto" else 1), lines
    assert mode == "active" or "no point cloud, so they are triangulated" in lines[0]
    assert lines[-1].startswith("seed points: ") and int(lines[-1].split()[2]) == num_points >= 100


def test_colmap_initial_outside_colmap_is_a_one_line_error(fox, tmp_path):
    cfg = short_config(fox, tmp_path, steps=4, seed_points="colmap-initial")
    cfg.pipeline.datamanager.dataparser = HpgsNerfstudioDataParserConfig(data=fox, downscale_factor=4)
    with pytest.raises(ActiveViewError, match="seed-points colmap-initial needs COLMAP point tracks"):
        run_training(cfg)


def plan(select_every=2000, select_at=(), max_rounds=7, views_per_round=1, candidates=100, history=(), steps=15000):
    config = SelectionConfig(select_every=select_every, select_at=select_at, max_rounds=max_rounds,
                             views_per_round=views_per_round, selector="random")
    dm = SimpleNamespace(config=SimpleNamespace(seed=0), history=[SimpleNamespace(step=s) for s in history],
                         candidates=list(range(candidates)))
    return SelectionRounds(config, dm, model=None, selector=object()).plan(0 if not history else history[-1], steps)


def test_the_round_plan_says_why_fewer_rounds_run():
    assert plan() == (7, "")
    assert plan(select_every=0) == (0, "select-every 0 and no select-at")
    assert plan(max_rounds=0) == (0, "max-rounds 0")
    assert plan(select_every=5000) == (2, "select-every 5000 leaves 2 round steps before the last step (14999)")
    assert plan(select_at=(400, 20000)) == (1, "only 1 select-at steps come before the last step (14999)")
    assert plan(candidates=3) == (3, "only 3 withheld views to add (1 per round)")
    assert plan(candidates=5, views_per_round=2) == (3, "only 5 withheld views to add (2 per round)")
    assert plan(candidates=0) == (0, "no withheld views to add (the initial views are the whole training split)")
    assert plan(history=(2000, 4000, 6000, 8000, 10000, 12000, 14000)) == (0, "all 7 rounds already ran")


def test_a_run_that_will_not_select_says_so_at_start(tiny_scene, tmp_path, capsys):
    run_training(short_config(tiny_scene, tmp_path, steps=6, every=0))
    assert "no selection rounds will run: select-every 0 and no select-at" in capsys.readouterr().out
