"""One line for every bad input (#32): each names the thing and the fix, exits non-zero, and leaves nothing
half-written (no run folder, no partial images_N, no checkpoint).

Option values are checked while tyro parses the command line (the configs' `__post_init__`), before nerfstudio
prints its config or makes a run folder: tested in-process, as `ns-train hpgs` parses them. Scene problems are
found at set-up; a set-up that fails removes the run folder ns-train made for it. One `ns-train` subprocess checks
what a user sees for a bad option: the `error: ...` line, exit 1, no config dump, no run folder (test_errors.py's
does for a bad scene path).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import tyro
import yaml
from conftest import run_training, short_config
from helpers import make_capture
from PIL import Image

from hpgs_ns.dataparser import HpgsNerfstudioDataParserConfig, MipNerf360DataParserConfig, SceneDataError
from hpgs_ns.errors import OptionError, UserError
from hpgs_ns.method_config import hpgs_trainer_config
from hpgs_ns.scenes.synthetic import make_scene

ENV = {k: v for k, v in os.environ.items() if k != "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD"}


def parse(args):
    """`ns-train hpgs`'s options after the method name, parsed in-process as tyro parses them there."""
    default = hpgs_trainer_config(100)
    return tyro.cli(type(default), default=default, args=args)


# (command line, the start of the message: the flag and its value, the fix it gives)
BAD_OPTIONS = [
    (["--pipeline.selection.views-per-round", "0"], "--pipeline.selection.views-per-round 0: must be at least 1",
     "pass 1 or more (--pipeline.selection.max-rounds 0 runs no rounds)"),
    (["--pipeline.selection.select-every", "-5"], "--pipeline.selection.select-every -5: must be >= 0",
     "pass 0 for no periodic rounds"),
    (["--pipeline.selection.select-at", "400", "0"], "--pipeline.selection.select-at 400 0: round steps must be >= 1",
     "drop the steps below 1"),
    (["--pipeline.selection.max-rounds", "-1"], "--pipeline.selection.max-rounds -1: must be >= 0", "pass 0 for no rounds"),
    (["--pipeline.selection.snapshot-every", "-1"], "--pipeline.selection.snapshot-every -1: must be >= 0",
     "pass 0 for no snapshots"),
    (["--pipeline.selection.render-short-side", "0"], "--pipeline.selection.render-short-side 0: must be at least 1 pixel",
     "leave it out"),
    (["--pipeline.selection.stop-when-gain-below", "nan"], "--pipeline.selection.stop-when-gain-below nan: must be a finite",
     "leave it out to run every round"),
    (["--pipeline.datamanager.num-initial-views", "0"], "--pipeline.datamanager.num-initial-views 0: must be at least 1",
     "pass 1 or more"),
    (["--pipeline.datamanager.camera-res-scale-factor", "0"],
     "--pipeline.datamanager.camera-res-scale-factor 0.0: must be > 0", "pass e.g. 0.5"),
    (["--pipeline.datamanager.max-thread-workers", "0"], "--pipeline.datamanager.max-thread-workers 0: must be at least 1",
     "leave it out"),
    (["mipnerf360", "--downscale-factor", "0"], "mipnerf360 --downscale-factor 0: must be at least 1",
     "pass 1, 2, 4, ... or leave it out"),
    (["mipnerf360", "--eval-interval", "0"], "mipnerf360 --eval-interval 0: must be at least 1", "pass e.g. 8"),
    (["mipnerf360", "--max-unreadable-fraction", "1.5"], "mipnerf360 --max-unreadable-fraction 1.5: must be within [0, 1]",
     "pass e.g. 0.1"),
    (["--pipeline.selection.selector", "nosuch"], "--pipeline.selection.selector nosuch: unknown selector",
     "choose one of random, farthest, fisher, coverage, hpgs"),
    (["nerfstudio-data", "--train-split-fraction", "1"], "nerfstudio-data --train-split-fraction 1.0: must be within (0, 1)",
     "pass e.g. 0.9"),
]


@pytest.mark.parametrize("args,start,fix", BAD_OPTIONS, ids=[" ".join(row[0]) for row in BAD_OPTIONS])
def test_a_bad_option_value_is_one_line_while_the_command_line_is_parsed(args, start, fix):
    with pytest.raises(OptionError) as info:
        parse(args)
    message = str(info.value)
    assert message.startswith(start) and fix in message and "\n" not in message
    assert not isinstance(info.value, ValueError)  # tyro would catch it and draw its own box


def test_sensible_values_parse_and_configs_built_in_code_or_read_from_yaml_are_not_checked(tmp_path):
    cfg = parse(["--pipeline.selection.select-every", "0", "--pipeline.selection.max-rounds", "0",
                 "--pipeline.selection.stop-when-gain-below", "-0.5", "--pipeline.datamanager.num-initial-views", "0",
                 "--pipeline.datamanager.initial-view-names", "images/0001.png", "mipnerf360", "--downscale-factor", "1"])
    selection = cfg.pipeline.selection
    assert (selection.select_every, selection.max_rounds, cfg.pipeline.datamanager.num_initial_views) == (0, 0, 0)
    # scripts set values after building a config (tests/conftest.py's short_config): nothing checks those
    cfg.pipeline.selection.views_per_round = 0
    # a config.yml is read without __init__ (so without __post_init__): an old file with any value still opens
    text = yaml.dump(cfg)
    assert "views_per_round: 0" in text
    assert yaml.load(text, Loader=yaml.Loader).pipeline.selection.views_per_round == 0


def test_ns_train_with_a_bad_option_prints_one_line_before_any_config_dump_or_run_folder(tiny_scene, tmp_path):
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "nerfstudio.scripts.train", "hpgs", "--data", str(tiny_scene), "--output-dir", str(out),
           "--vis", "tensorboard", "--pipeline.model.rasterizer", "cpu", "--pipeline.selection.views-per-round", "0"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=ENV)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1] == (
        "error: --pipeline.selection.views-per-round 0: must be at least 1 (the views each round adds); pass 1 or more "
        "(--pipeline.selection.max-rounds 0 runs no rounds)")
    assert "Traceback" not in proc.stderr and "HpgsTrainerConfig" not in proc.stdout  # no config dump
    assert not out.exists()


# ---- scenes ---------------------------------------------------------------------------------------------------


@pytest.fixture
def small_scene(tmp_path) -> Path:
    """A 16-camera COLMAP scene of 64x48 PNGs (test views: 0000 and 0008)."""
    return make_scene(tmp_path / "scene", layout="ring", num_cameras=16, width=64, height=48, num_points=300, seed=0)


def test_one_photo_of_another_size_names_it_and_the_fix_and_the_failed_setup_leaves_no_run_folder(small_scene, tmp_path):
    photo = small_scene / "images" / "0005.png"
    with Image.open(photo) as image:
        image.resize((40, 30)).save(photo)
    cfg = short_config(small_scene, tmp_path / "out", steps=4)
    with pytest.raises(SceneDataError) as info:
        run_training(cfg)
    assert str(info.value) == (f"{photo} is 40x30 but its camera says 64x48; replace it with the 64x48 photo its camera "
                               f"was made from, or remove it from the COLMAP model ({small_scene / 'sparse' / '0'})")
    assert not (tmp_path / "out" / "test").exists()


def test_a_failed_setup_keeps_a_run_folder_that_holds_more_than_its_config(small_scene, tmp_path):
    cfg = short_config(small_scene, tmp_path / "out", steps=4)
    cfg.pipeline.datamanager.data = cfg.data = tmp_path / "nope"
    cfg.set_timestamp()
    cfg.save_config()
    kept = cfg.get_base_dir() / "notes.txt"
    kept.write_text("mine")
    trainer = cfg.setup(local_rank=0, world_size=1)
    with pytest.raises(SceneDataError, match="does not exist"):
        trainer.setup()
    assert kept.read_text() == "mine" and (cfg.get_base_dir() / "config.yml").is_file()


def test_a_truncated_photo_is_dropped_with_images_n_written_for_it_and_the_run_trains(small_scene, tmp_path):
    photo = small_scene / "images" / "0003.png"
    photo.write_bytes(photo.read_bytes()[:200])
    for attempt in ("writes images_2", "reads the images_2 it wrote"):
        outputs = {s: MipNerf360DataParserConfig(data=small_scene, downscale_factor=2).setup().get_dataparser_outputs(s)
                   for s in ("train", "test")}
        names = {s: [Path(p).name for p in o.image_filenames] for s, o in outputs.items()}
        assert names["test"] == ["0000.png", "0008.png"], attempt
        assert len(names["train"]) == 13 and "0003.png" not in names["train"], attempt
    assert not (small_scene / "images_2" / "0003.png").exists()
    cfg = short_config(small_scene, tmp_path / "out", steps=4, every=2, rounds=1, initial=4, selector="random")
    cfg.pipeline.datamanager.dataparser.downscale_factor = 2
    trainer = run_training(cfg)
    assert trainer.pipeline.datamanager.image_names[2] == "images/0004.png"  # 0003 dropped
    assert (trainer.checkpoint_dir / "step-000000003.ckpt").is_file()


def capture_error(folder: Path, **options) -> str:
    with pytest.raises(SceneDataError) as info:
        HpgsNerfstudioDataParserConfig(data=folder, **options).setup().get_dataparser_outputs("train")
    return str(info.value)


def test_transforms_json_problems_name_the_file_and_write_nothing(tmp_path):
    truncated = make_capture(tmp_path / "truncated")
    meta = truncated / "transforms.json"
    meta.write_text(meta.read_text()[:300])
    message = capture_error(truncated)
    assert message.startswith(f"{meta} is not readable JSON (") and message.endswith(
        "; restore it from the capture or re-run ns-process-data")

    missing = make_capture(tmp_path / "missing")
    (missing / "images" / "0002.png").unlink()
    expected = (f"1 images named in {missing / 'transforms.json'} are missing, e.g. {missing / 'images' / '0002.png'}; "
                "restore them or remove their frames from transforms.json")
    assert capture_error(missing) == expected
    assert capture_error(missing, downscale_factor=2) == expected
    assert sorted(p.name for p in missing.iterdir()) == ["images", "transforms.json"]  # no images_2, whole or half

    unreadable = make_capture(tmp_path / "unreadable")
    (unreadable / "images" / "0002.png").write_bytes(b"")
    message = capture_error(unreadable, downscale_factor=2)
    assert message.startswith(f"cannot read {unreadable / 'images' / '0002.png'} (") and message.endswith(
        f"; restore it or remove it from {unreadable / 'transforms.json'}")
    assert sorted(p.name for p in unreadable.iterdir()) == ["images", "transforms.json"]


def test_data_naming_a_file_says_it_is_a_file(small_scene, tmp_path):
    def error(config) -> str:
        with pytest.raises(SceneDataError) as info:
            config.setup().get_dataparser_outputs("train")
        return str(info.value)

    photo = small_scene / "images" / "0001.png"
    assert error(MipNerf360DataParserConfig(data=photo)) == f"--data {photo} is a file, not a scene folder; pass --data {small_scene}"
    capture = make_capture(tmp_path / "capture")
    assert error(MipNerf360DataParserConfig(data=capture / "transforms.json")) == (
        f"--data {capture / 'transforms.json'} is a file, not a scene folder; run: ns-train hpgs [options] nerfstudio-data "
        f"--data {capture}")
    stray = tmp_path / "notes.txt"
    stray.write_text("x")
    assert error(MipNerf360DataParserConfig(data=stray)).endswith(
        "is a file, not a scene folder; pass --data the scene folder (the one holding images/ and sparse/0/)")
    assert error(HpgsNerfstudioDataParserConfig(data=capture / "images" / "0001.png")) == (
        f"--data {capture / 'images' / '0001.png'} is a file, not a capture folder; pass the folder holding "
        "transforms.json (or the transforms.json itself)")


def test_train_pref_without_pairs_names_the_option(tmp_path):
    from hpgs_ns.preference.train import TrainPref

    out = tmp_path / "model.pt"
    command = tyro.cli(TrainPref, args=["--out", str(out)])
    with pytest.raises(UserError) as info:
        command.main()
    assert str(info.value) == ("hpgs train-pref: --pairs is required: pass --pairs PAIRS.csv (written by `hpgs label DIR`); "
                               "repeat it for several files")
    assert list(tmp_path.iterdir()) == []


def test_data_naming_a_file_or_nothing_is_one_line_while_ns_train_parses(small_scene, tmp_path):
    from hpgs_ns.method_config import hpgs_trainer_config

    default = hpgs_trainer_config(100)
    photo = small_scene / "images" / "0001.png"
    with pytest.raises(OptionError, match=f"^--data {photo} is a file, not a scene folder; pass --data {small_scene}$"):
        tyro.cli(type(default), default=default, args=["--data", str(photo)])
    with pytest.raises(OptionError, match="does not exist; pass --data PATH"):
        tyro.cli(type(default), default=default, args=["--data", str(tmp_path / "nowhere")])
    assert tyro.cli(type(default), default=default, args=["--data", str(small_scene)]).data == small_scene


def test_ns_train_says_one_line_for_its_config_instead_of_dumping_it(tiny_scene, capsys):
    from hpgs_ns.method_config import hpgs_trainer_config

    cfg = hpgs_trainer_config(100)
    cfg.data = cfg.pipeline.datamanager.data = tiny_scene
    cfg.print_to_terminal()
    out = " ".join(capsys.readouterr().out.split())
    assert out.startswith("hpgs: selector farthest, 100 steps, data ") and out.endswith("config.yml")
    assert str(tiny_scene) in out.replace(" ", "") or str(tiny_scene) in out
