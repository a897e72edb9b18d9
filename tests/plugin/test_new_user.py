"""What a new user hits first (issue #65): a scene that ships only `images_N/`, runs whose checkpoint or config.yml
is damaged or missing, a copied run folder, and the small one-line errors.

The ns-eval, ns-viewer and copied-folder cases share one 10-step CPU run (`run`). nerfstudio's entry points are
called in-process with `sys.argv` set as the shell would (a second Python costs more than the run); what an
uncaught exception prints under them is what the plugin's excepthook makes of it (`one_line`); Python exits 1
after any uncaught exception.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest
import yaml
from conftest import run_training, short_config
from helpers import one_line
from PIL import Image

import hpgs_ns.method_config  # noqa: F401 (what nerfstudio imports: it installs the excepthook and its explainer)
from hpgs_ns.dataparser import MipNerf360DataParserConfig, SceneDataError
from hpgs_ns.errors import UserError, print_user_errors

# ---- 1. a scene with images_N/ and sparse/0/ but no images/ -----------------------------------------------------


@pytest.fixture
def half_only(tmp_path) -> Path:
    """A 16-camera synthetic scene whose COLMAP cameras are 64x48 and whose only photos are images_2/ (32x24)."""
    from hpgs_ns.scenes.synthetic import make_scene

    scene = make_scene(tmp_path / "half", layout="ring", num_cameras=16, width=64, height=48, num_points=200, seed=0)
    (scene / "images_2").mkdir()
    for photo in sorted((scene / "images").iterdir()):
        with Image.open(photo) as image:
            image.resize((32, 24), Image.Resampling.BICUBIC).save(scene / "images_2" / photo.name)
    shutil.rmtree(scene / "images")
    return scene


def test_a_scene_with_only_images_n_trains_from_it_and_says_so_in_one_line(half_only, capsys):
    parser = MipNerf360DataParserConfig(data=half_only).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    said = capsys.readouterr().out
    assert said.count(f"{half_only / 'images'} does not exist: reading the photos in {half_only / 'images_2'}") == 1
    assert "(as mipnerf360 --downscale-factor 2)" in said and said.count("\n") == 1
    assert {Path(p).parent.name for p in train.image_filenames + test.image_filenames} == {"images_2"}
    assert (int(train.cameras.width[0]), int(train.cameras.height[0])) == (32, 24)  # the cameras scaled to the photos
    assert len(train.image_filenames) + len(test.image_filenames) == 16
    assert sorted(p.name for p in half_only.iterdir() if p.is_dir()) == ["images_2", "sparse"]  # none written or deleted


def test_images_path_images_n_gives_the_one_right_command_and_never_says_delete(half_only):
    with pytest.raises(SceneDataError) as info:
        MipNerf360DataParserConfig(data=half_only, images_path=Path("images_2")).setup().get_dataparser_outputs("train")
    photo = half_only / "images_2" / "0001.png"
    assert str(info.value) == (
        f"{photo} is 32x24 but its camera says 64x48: {half_only / 'images_2'} holds the photos at 1/2 of their cameras' "
        "size; pass mipnerf360 --downscale-factor 2 instead of --images-path images_2 (it reads "
        f"{half_only / 'images_2'} and scales the cameras to it)")
    with pytest.raises(SceneDataError) as info:  # a factor with no folder, and no images/ to write one from
        MipNerf360DataParserConfig(data=half_only, downscale_factor=4).setup().get_dataparser_outputs("train")
    assert str(info.value) == (f"{half_only / 'images_4'} does not exist and there is no {half_only / 'images'} to write "
                               f"it from; the photos are in {half_only / 'images_2'}: pass mipnerf360 --downscale-factor 2")


def test_a_wrong_photo_in_the_only_images_n_is_named_and_the_folder_is_kept(half_only):
    Image.new("RGB", (20, 15)).save(half_only / "images_2" / "0005.png")
    with pytest.raises(SceneDataError) as info:
        outputs = MipNerf360DataParserConfig(data=half_only, downscale_factor=2).setup().get_dataparser_outputs("train")
        from hpgs_ns.dataparser import check_image_sizes

        check_image_sizes([type("D", (), {"image_filenames": outputs.image_filenames, "cameras": outputs.cameras})()],
                          MipNerf360DataParserConfig(data=half_only))
    message = str(info.value)
    assert "delete" not in message, message  # images_2 is the only copy: nothing could write it again
    assert message == (f"{half_only / 'images_2' / '0005.png'} is 20x15 but its camera says 32x24; there is no "
                       f"{half_only / 'images' / '0005.png'} to write it from, so {half_only / 'images_2'} holds the only "
                       "copy: replace 0005.png with the 32x24 photo its camera was made from, or remove it from the COLMAP "
                       f"model ({half_only / 'sparse' / '0'})")


def test_the_shared_gum_jar_capture_reads_as_it_is(tmp_path):
    """The new captures in ../shared/data ship images_2/ and sparse/0/ only (a copy: the shared folder is read-only)."""
    from conftest import require_shared

    source = require_shared("data", "gum-jar")
    scene = tmp_path / "gum-jar"
    shutil.copytree(source / "sparse", scene / "sparse")
    shutil.copytree(source / "images_2", scene / "images_2")
    outputs = MipNerf360DataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    assert Path(outputs.image_filenames[0]).parent == scene / "images_2"
    assert (int(outputs.cameras.width[0]), int(outputs.cameras.height[0])) == (224, 401)


# ---- 3 and 4. ns-eval and ns-viewer on a damaged, empty or copied run --------------------------------------------


@pytest.fixture(scope="module")
def run(tiny_scene, tmp_path_factory) -> Path:
    """One 10-step CPU run with no rounds (its one checkpoint at step 9); tests copy it before they change it."""
    out = tmp_path_factory.mktemp("runs")
    cfg = short_config(tiny_scene, out, steps=10, rounds=0)
    run_training(cfg)
    folder = out / "test" / "hpgs" / "run"
    assert [p.name for p in (folder / "nerfstudio_models").iterdir()] == ["step-000000009.ckpt"]
    return folder


def copy_run(run: Path, where: Path, own: bool = False) -> Path:
    """The run folder copied elsewhere, as a user copies one (its config.yml keeps the original's output path), or
    with `own` a run of its own there (its config.yml names the copy, as if trained there)."""
    copy = where / "copied" / "test" / "hpgs" / "run"
    shutil.copytree(run, copy)
    if own:
        config = yaml.load((copy / "config.yml").read_text(), Loader=yaml.Loader)
        config.output_dir = where / "copied"
        (copy / "config.yml").write_text(yaml.dump(config))
    return copy


def nerfstudio_cli(monkeypatch, module, *args) -> BaseException:
    """Run nerfstudio's `module.entrypoint()` with `sys.argv` as the shell passes it; it must fail. Returns what it
    raised (SystemExit included). ns-viewer that did load the run would serve forever: its viewer start fails the
    test instead (a hang guard)."""
    monkeypatch.setattr(sys, "argv", [module.__name__, *map(str, args)])
    if hasattr(module, "_start_viewer"):
        monkeypatch.setattr(module, "_start_viewer", lambda *a: pytest.fail("ns-viewer loaded the run and started"))
    with pytest.raises(BaseException) as info:  # noqa: B017 (whatever nerfstudio raises: the test says what it must be)
        module.entrypoint()
    return info.value


def ns_eval():
    from nerfstudio.scripts import eval as ns_eval_module

    return ns_eval_module


def ns_viewer():
    from nerfstudio.scripts.viewer import run_viewer

    return run_viewer


def test_ns_eval_of_a_copied_run_loads_the_copy_s_own_checkpoint_and_says_why(run, tmp_path, monkeypatch, capsys):
    """ns-eval (and ns-viewer) open a run with nerfstudio's `eval_setup`; the checkpoint it returns is the one
    loaded, and the one ns-eval's JSON names."""
    from nerfstudio.utils.eval_utils import eval_setup

    copy = copy_run(run, tmp_path)
    (copy / "nerfstudio_models" / "step-000000009.ckpt").rename(copy / "nerfstudio_models" / "step-000000008.ckpt")
    monkeypatch.setattr(sys, "argv", ["ns-eval", "--load-config", str(copy / "config.yml")])
    _, _, checkpoint, step = eval_setup(copy / "config.yml")
    assert (checkpoint, step) == (copy / "nerfstudio_models" / "step-000000008.ckpt", 8)  # the copy's, told apart by name
    said = [line for line in capsys.readouterr().out.splitlines() if "the output path it was trained with" in line]
    assert said == [f"{copy / 'config.yml'} names {run / 'nerfstudio_models'} as its checkpoints (the output path it was "
                    f"trained with); loading the ones beside it, in {copy / 'nerfstudio_models'}"]
    _, _, checkpoint, _ = eval_setup(run / "config.yml")  # the original still opens its own, and says nothing
    assert checkpoint == run / "nerfstudio_models" / "step-000000009.ckpt"
    assert "the output path it was trained with" not in capsys.readouterr().out


@pytest.mark.parametrize("cli", [ns_eval, ns_viewer], ids=["ns-eval", "ns-viewer"])
def test_a_truncated_checkpoint_is_one_line_naming_it(run, tmp_path, monkeypatch, cli):
    copy = copy_run(run, tmp_path, own=True)
    ckpt = copy / "nerfstudio_models" / "step-000000009.ckpt"
    ckpt.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])  # a copy that stopped
    err = nerfstudio_cli(monkeypatch, cli(), "--load-config", copy / "config.yml")
    assert type(err) is RuntimeError and "PytorchStreamReader" in str(err)  # nerfstudio's own, from torch.load
    line = one_line(err)
    assert line.startswith(f"{ckpt} does not load (RuntimeError: PytorchStreamReader failed reading zip archive")
    assert line.endswith("); it is probably truncated; it is the run's only checkpoint: restore it from a copy, or train "
                         "the run again")
    # with an older checkpoint beside it, the line says which one loads once it is moved away
    shutil.copy(run / "nerfstudio_models" / "step-000000009.ckpt", copy / "nerfstudio_models" / "step-000000004.ckpt")
    line = one_line(nerfstudio_cli(monkeypatch, cli(), "--load-config", copy / "config.yml"))
    assert line.endswith(f"; move it out of {copy / 'nerfstudio_models'} to load the one before it (step-000000004.ckpt)")


@pytest.mark.parametrize("cli", [ns_eval, ns_viewer], ids=["ns-eval", "ns-viewer"])
def test_a_run_without_a_checkpoint_is_one_line(run, tmp_path, monkeypatch, cli):
    copy = copy_run(run, tmp_path)
    (copy / "nerfstudio_models" / "step-000000009.ckpt").unlink()  # the folder is there, empty: nerfstudio's IndexError
    moved = tmp_path / "moved"
    shutil.move(run / "nerfstudio_models", moved)  # and the original's folder gone: nerfstudio's SystemExit box
    try:
        err = nerfstudio_cli(monkeypatch, cli(), "--load-config", copy / "config.yml")
    finally:
        shutil.move(moved, run / "nerfstudio_models")
    assert one_line(err) == (
        f"no checkpoint to load: {copy / 'nerfstudio_models'} holds no step-*.ckpt, nor does {run / 'nerfstudio_models'}, "
        "the folder config.yml names; train the run first (it saves one every --steps-per-save steps and at its last), "
        "or copy the run's nerfstudio_models there")


def test_ns_train_load_config_of_a_damaged_config_yml_is_one_line(run, tmp_path, monkeypatch):
    from nerfstudio.scripts import train

    damaged = tmp_path / "config.yml"
    text = (run / "config.yml").read_text()
    damaged.write_text(text.replace("hpgs_ns.pipeline.HpgsPipelineConfig", "hpgs_ns.pipeline.NoSuchConfig"))
    config = yaml.load(text, Loader=yaml.Loader)
    config.load_config = damaged
    monkeypatch.setattr(sys, "argv", ["ns-train", "hpgs", "--load-config", str(damaged)])
    with pytest.raises(yaml.constructor.ConstructorError) as info:
        train.main(config)
    line = one_line(info.value)
    assert line.startswith(f"{damaged} is not a readable run config (ConstructorError: ")
    assert line.endswith("; restore it, or pass the config.yml a training run wrote (outputs/<experiment>/<method>/<timestamp>/)")
    # the same error raised elsewhere keeps its traceback
    fallen = []
    monkeypatch.setattr(sys, "argv", ["ns-train"])
    print_user_errors(type(info.value), info.value, info.value.__traceback__, lambda *a: fallen.append(a[0]))
    assert fallen == [yaml.constructor.ConstructorError] and not isinstance(info.value, UserError)


# ---- 6. the small ones ---------------------------------------------------------------------------------------


def test_the_0_2_spelling_of_selection_options_stops_with_one_line_naming_the_new_one(monkeypatch):
    """ns-train imports the method module before tyro parses the command line (tyro's answer: a 39-line box, exit 2);
    the OptionError there prints as one line, and Python exits 1."""
    import importlib

    from hpgs_ns.errors import OptionError

    session = sys.modules["hpgs_ns.method_config"]  # the module as the session imported it
    argv = ["/venv/bin/ns-train", "hpgs", "--data", "s", "--pipeline.datamanager.selector", "random",
            "--pipeline.datamanager.fisher.probes=8", "--pipeline.datamanager.select-at", "400", "900",
            "--pipeline.datamanager.selection-short-side", "64", "--pipeline.datamanager.seed", "3"]
    monkeypatch.setattr(sys, "argv", argv)
    monkeypatch.delitem(sys.modules, "hpgs_ns.method_config")  # put back after the test
    with pytest.raises(OptionError) as info:
        importlib.import_module("hpgs_ns.method_config")
    assert one_line(info.value) == (
        "--pipeline.datamanager.selector random --pipeline.datamanager.fisher.probes=8 --pipeline.datamanager.select-at "
        "400 900 --pipeline.datamanager.selection-short-side 64: the 0.2 spelling of the selection options, removed in "
        "0.4; pass --pipeline.selection.selector random --pipeline.selection.fisher.probes=8 --pipeline.selection.select-at "
        "400 900 --pipeline.selection.render-short-side 64")

    for fine in (["ns-train", "hpgs", "--pipeline.datamanager.seed", "3", "--pipeline.selection.selector", "random"],
                 ["ns-train", "splatfacto", "--pipeline.datamanager.selector", "x"], ["ns-eval", "--load-config", "c"]):
        session.reject_removed_spelling(fine)  # nothing to say


@pytest.mark.parametrize("command", ["eval-pref", "train-pref"])
def test_eval_pref_and_train_pref_without_pairs_say_the_same_one_line(monkeypatch, tmp_path, command):
    from helpers import hpgs_error

    options = ["--model", tmp_path / "m.pt"] if command == "eval-pref" else ["--out", tmp_path / "m.pt"]
    assert hpgs_error(monkeypatch, command, *options) == (
        f"hpgs {command}: --pairs is required: pass --pairs PAIRS.csv (written by `hpgs label DIR`); repeat it for "
        "several files")  # a UserError: exit 1, as every one-line error


def test_a_colmap_count_that_overruns_the_file_is_told_with_numbers_that_agree(tiny_scene, tmp_path):
    import re
    import struct

    from hpgs_ns.scenes.colmap_model import ColmapModelError, read_model_file

    images = tmp_path / "images.bin"
    data = bytearray((tiny_scene / "sparse" / "0" / "images.bin").read_bytes())
    at = data.index(b"\x00", 8 + 64) + 1  # the first image's keypoint count: after its count, record and name
    struct.pack_into("<Q", data, at, len(data) // 24 - 1)  # fewer records than the whole file holds, more than follow
    images.write_bytes(bytes(data))
    with pytest.raises(ColmapModelError) as info:
        read_model_file(images)
    found = re.search(r"a count at byte (\d+) says (\d+) records of at least (\d+) bytes follow, but only (\d+) of its "
                      r"(\d+) bytes are left", str(info.value))
    assert found, str(info.value)
    start, n, each, left, total = map(int, found.groups())
    assert (start, n, total) == (at, len(data) // 24 - 1, len(data)) and left == total - at - 8 and n * each > left


def test_densification_lines_after_a_restart_name_the_run_s_step(tiny_scene, tmp_path, capsys):
    from conftest import short_config
    from helpers import train_steps

    cfg = short_config(tiny_scene, tmp_path, steps=300, rounds=0)
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    model.reset_to_initial(200, trainer.optimizers.optimizers)  # what an after-add restart at step 200 does
    model.strategy.pause_refine_after_reset = 0  # densify at the first refine step the restart's clock reaches
    capsys.readouterr()
    train_steps(trainer, [240])  # the model's step 40: a refine step
    said = [line for line in capsys.readouterr().out.splitlines() if "GSs" in line]
    assert len(said) == 2 and all(line.startswith("Step 240 (step 40 since the restart at step 200): ") for line in said)
    assert "GSs duplicated" in said[0] and "GSs pruned" in said[1]
