"""Every file the project reads fails with one line naming the file and the fix (#44), never another exception:
COLMAP models (.bin and .txt), transforms.json, images, pairs CSVs, suite TOML, a run's config.yml (hpgs suggest,
ns-eval/ns-viewer), selected_views.json, checkpoints, preference models and bench results.

Commands are run as `hpgs` runs them (`hpgs_ns.cli.entrypoint`, in-process) and their failure printed by the
excepthook it installs: one `error: ...` line on stderr, and an uncaught exception (exit 1); one subprocess checks
the exit status and that nothing else is printed. Each case also checks that nothing is left half-written.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from helpers import hpgs_error, make_capture, one_line
from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils
from PIL import Image

from hpgs_ns.dataparser import HpgsNerfstudioDataParserConfig, MipNerf360DataParserConfig, SceneDataError
from hpgs_ns.errors import UserError, print_user_errors
from hpgs_ns.preference.model import PreferenceModel
from hpgs_ns.preference.recipe import PreferenceModelError
from hpgs_ns.run_config import RunConfigError, read_run_config
from hpgs_ns.scenes.colmap_model import ColmapModelError, read_model_file
from hpgs_ns.scenes.synthetic import make_scene
from hpgs_ns.selection.log import RoundLogError, SelectionLog
from hpgs_ns.trainer import CheckpointError, load_checkpoint_file

REPO = Path(__file__).resolve().parents[2]


# ---- COLMAP models --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def colmap_scene(tmp_path_factory) -> Path:
    return make_scene(tmp_path_factory.mktemp("colmap") / "scene", layout="ring", num_cameras=12, width=32, height=24,
                      num_points=200, seed=0)


def text_model(scene: Path, into: Path) -> Path:
    """A copy of `scene` whose COLMAP model is in the text format."""
    import shutil

    shutil.copytree(scene, into)
    model = into / "sparse" / "0"
    for stem, write in (("cameras", colmap_utils.write_cameras_text), ("images", colmap_utils.write_images_text),
                        ("points3D", colmap_utils.write_points3D_text)):
        write(read_model_file(model / f"{stem}.bin"), model / f"{stem}.txt")
        (model / f"{stem}.bin").unlink()
    return into


def cut(fraction=None, size=None):
    def damage(path: Path) -> None:
        data = path.read_bytes()
        path.write_bytes(data[: size if size is not None else int(len(data) * fraction)])
    return damage


def replace_line(index: int, text: str):
    def damage(path: Path) -> None:
        lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
        lines[index] = text
        path.write_text("\n".join(lines) + "\n")
    return damage


# (model file, damage, what the line says)
COLMAP_CASES = [
    ("cameras.bin", cut(size=20), "cameras.bin is not a readable COLMAP cameras file"),
    ("points3D.bin", cut(fraction=0.5), "points3D.bin is not a readable COLMAP points3D file"),
    ("images.bin", cut(size=0), "images.bin is not a readable COLMAP images file"),
    ("images.bin", cut(fraction=0.7), "images.bin is not a readable COLMAP images file"),
    ("cameras.txt", replace_line(0, "1 PINHOLE 32 twenty-four 1 2 3 4"), "cameras.txt is not a readable COLMAP cameras file"),
    ("images.txt", replace_line(0, "1 0.5 0.5"), "images.txt is not a readable COLMAP images file"),
    ("points3D.txt", replace_line(3, "7 0.1 0.2"), "points3D.txt is not a readable COLMAP points3D file"),
]


@pytest.mark.parametrize("name,damage,says", COLMAP_CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(COLMAP_CASES)])
def test_a_damaged_colmap_model_file_is_one_line_naming_it(colmap_scene, tmp_path, name, damage, says):
    scene = text_model(colmap_scene, tmp_path / "scene") if name.endswith(".txt") else colmap_scene
    if not name.endswith(".txt"):
        import shutil

        scene = Path(shutil.copytree(colmap_scene, tmp_path / "scene"))
    path = scene / "sparse" / "0" / name
    damage(path)
    with pytest.raises(ColmapModelError):
        read_model_file(path)
    with pytest.raises(SceneDataError) as info:
        MipNerf360DataParserConfig(data=scene, downscale_factor=2).setup().get_dataparser_outputs("train")
    line = one_line(info.value)
    assert line.startswith(f"{path} ") and says in line and line.endswith("restore it from the source or re-run COLMAP")
    assert not (scene / "images_2").exists() and not list(scene.glob(".images_2-*"))  # nothing half-written


def test_the_text_and_binary_readers_give_nerfstudios_tuples(colmap_scene, tmp_path):
    model = colmap_scene / "sparse" / "0"
    text = text_model(colmap_scene, tmp_path / "text") / "sparse" / "0"
    for stem, stock in (("cameras", colmap_utils.read_cameras_binary), ("images", colmap_utils.read_images_binary),
                        ("points3D", colmap_utils.read_points3D_binary)):
        ours, theirs, as_text = read_model_file(model / f"{stem}.bin"), stock(model / f"{stem}.bin"), read_model_file(text / f"{stem}.txt")
        assert list(ours) == list(theirs) == list(as_text)
        for key in ours:
            for a, b in zip(ours[key], theirs[key]):
                assert (a == b).all() if hasattr(a, "shape") else a == b


# ---- transforms.json ------------------------------------------------------------------------------------------


TRANSFORMS_CASES = [
    ("fl_x", "abc"), ("w", [32]), ("h", None), ("frames.0.transform_matrix", "x"),
    ("frames.1.transform_matrix", [[1, 0], [0, 1]]), ("frames.2.file_path", 5), ("frames", {"a": 1}),
    ("ply_file_path", 7), ("camera_model", 3),
]


def set_path(tree, dotted: str, value):
    keys = [int(k) if k.isdigit() else k for k in dotted.split(".")]
    for key in keys[:-1]:
        tree = tree[key]
    tree[keys[-1]] = value


@pytest.mark.parametrize("field,value", TRANSFORMS_CASES, ids=[c[0] for c in TRANSFORMS_CASES])
def test_a_transforms_json_field_of_the_wrong_type_is_one_line(tmp_path, field, value):
    capture = make_capture(tmp_path / "capture")
    meta_path = capture / "transforms.json"
    meta = json.loads(meta_path.read_text())
    set_path(meta, field, value)
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(SceneDataError) as info:
        HpgsNerfstudioDataParserConfig(data=capture, downscale_factor=2).setup().get_dataparser_outputs("train")
    line = one_line(info.value)
    assert str(meta_path) in line and ("re-run ns-process-data" in line or "restore" in line), line
    assert sorted(p.name for p in capture.iterdir()) in (["images", "transforms.json"], ["images", "images_2", "transforms.json"])
    assert not list(capture.glob(".images_2-*"))


# ---- images under --downscale-factor: the source photo is named -----------------------------------------------


def test_a_wrong_sized_source_photo_is_named_not_images_n(colmap_scene, tmp_path):
    import shutil

    scene = Path(shutil.copytree(colmap_scene, tmp_path / "scene"))
    photo = scene / "images" / "0005.png"
    with Image.open(photo) as image:
        image.resize((20, 14)).save(photo)
    cfg = MipNerf360DataParserConfig(data=scene, downscale_factor=2)
    from nerfstudio.data.datasets.base_dataset import InputDataset

    from hpgs_ns.dataparser import check_image_sizes

    def error() -> str:
        outputs = cfg.setup().get_dataparser_outputs("train")
        with pytest.raises(SceneDataError) as info:
            check_image_sizes([InputDataset(outputs)], cfg)
        return one_line(info.value)

    line = error()
    assert line == (f"{scene / 'images_2' / '0005.png'} is 10x7 but its camera says 16x12; it is written from {photo}, "
                    f"which is 20x14, not 2x the camera's size: replace {photo} with the photo its camera was made from "
                    f"(then delete {scene / 'images_2'}), or remove it from the COLMAP model ({scene / 'sparse' / '0'})")
    shutil.rmtree(scene / "images_2")  # what the old advice said: the same photo is written again, the same line
    assert error() == line
    # written with the scene's usual permissions (mkdtemp's folder is 0700)
    assert (scene / "images_2").stat().st_mode & 0o777 == 0o777 & ~current_umask()


def current_umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


# ---- pairs CSVs (hpgs train-pref, hpgs eval-pref) -------------------------------------------------------------


@pytest.fixture
def pairs_folder(tmp_path) -> Path:
    for i in range(5):
        Image.new("RGB", (16, 16), (50 * i, 20, 20)).save(tmp_path / f"{i}.png")
    return tmp_path


PAIRS_CASES = [
    ("latin-1", "Image_1,Image_2,Human Preference\n0.png,caf\u00e9.png,1\n".encode("latin-1"), "not UTF-8 text (byte 0xe9"),
    ("binary", bytes(range(256)) * 4, "not UTF-8 text"),
    ("huge field", b"Image_1,Image_2,Human Preference\n0.png,\"" + b"x" * 200_000 + b"\",1\n",
     "not a readable CSV (field larger than field limit"),
]


@pytest.mark.parametrize("content,says", [c[1:] for c in PAIRS_CASES], ids=[c[0] for c in PAIRS_CASES])
@pytest.mark.parametrize("command", ["train-pref", "eval-pref"])
def test_a_pairs_csv_that_is_not_utf8_text_is_one_line(pairs_folder, monkeypatch, light_preference_model, command,
                                                       content, says):
    csv_path = pairs_folder / "pairs.csv"
    csv_path.write_bytes(content)
    out = pairs_folder / "model.pt"
    args = ["--pairs", csv_path, "--out", out] if command == "train-pref" else ["--model", light_preference_model, "--pairs", csv_path]
    line = hpgs_error(monkeypatch, command, *args)
    assert line.startswith(f"hpgs {command}: {csv_path}: {says}") and ("save it as UTF-8" in line or "fix the file" in line)
    assert not out.exists()


def test_train_pref_reads_every_labelled_image_and_refuses_an_empty_held_out_split(pairs_folder, monkeypatch):
    csv_path, out = pairs_folder / "pairs.csv", pairs_folder / "model.pt"
    # five images, every pair naming 0.png: the default --test-fraction 0.2 holds out 2, and no pair has both of them
    csv_path.write_text("Image_1,Image_2,Human Preference\n" + "".join(f"0.png,{i}.png,{i % 2}\n" for i in range(1, 5)))
    line = hpgs_error(monkeypatch, "train-pref", "--pairs", csv_path, "--out", out, "--input-size", "32")
    assert line.startswith(f"hpgs train-pref: {csv_path}: no held-out pairs at --test-fraction 0.2 (4 pairs over 5 images")
    assert line.endswith("or pass --test-fraction 0 to train on all of them without a held-out accuracy")
    (pairs_folder / "3.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)  # unreadable, in a training pair
    line = hpgs_error(monkeypatch, "train-pref", "--pairs", csv_path, "--out", out, "--test-fraction", "0")
    assert line.startswith(f"hpgs train-pref: {pairs_folder / '3.png'}: not a readable image (")
    assert line.endswith("; replace it or remove its pairs") and not out.exists()


def test_train_pref_with_test_fraction_0_says_there_is_no_held_out_accuracy(pairs_folder, monkeypatch, capsys):
    from hpgs_ns.cli import entrypoint

    csv_path, out = pairs_folder / "pairs.csv", pairs_folder / "model.pt"
    csv_path.write_text("Image_1,Image_2,Human Preference\n0.png,1.png,1\n1.png,2.png,0\n2.png,3.png,1\n")
    monkeypatch.setattr(sys, "argv", ["hpgs", "train-pref", "--pairs", str(csv_path), "--out", str(out),
                                      "--test-fraction", "0", "--input-size", "32"])
    entrypoint()
    assert "no held-out accuracy (--test-fraction 0: every pair trained)" in " ".join(capsys.readouterr().err.split())
    assert out.is_file()


def test_hpgs_train_pref_on_a_latin1_csv_prints_one_line_and_exits_1(pairs_folder):
    csv_path = pairs_folder / "pairs.csv"
    csv_path.write_bytes("Image_1,Image_2,Human Preference\n0.png,caf\u00e9.png,1\n".encode("latin-1"))
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-m", "hpgs_ns.cli", "train-pref", "--pairs", str(csv_path), "--out",
                           str(pairs_folder / "m.pt")], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.splitlines() == [f"error: hpgs train-pref: {csv_path}: not UTF-8 text (byte 0xe9 at offset 42); "
                                        "save it as UTF-8 CSV (or rewrite it with `hpgs collect`)"]


# ---- a run's config.yml (hpgs suggest, ns-eval, ns-viewer) ----------------------------------------------------


@pytest.fixture(scope="module")
def config_text() -> str:
    from hpgs_ns.method_config import hpgs_trainer_config

    return yaml.dump(hpgs_trainer_config(100))


CONFIG_CASES = [
    ("truncated", lambda text: text[: text.index("  model:")], "is cut short or damaged (it has no "),
    ("not YAML", lambda text: "key: [unclosed\n", "is not a readable run config (ParserError"),
    ("not a config", lambda text: "a: 1\n", "is not a nerfstudio run config (it holds a dict)"),
    ("Latin-1", lambda text: "caf\xe9: 1\n", "is not a readable run config (UnicodeDecodeError"),
    ("cut mid-line", lambda text: text[: len(text) // 3] + "\n  : :", "is not a readable run config"),
]


@pytest.mark.parametrize("make,says", [c[1:] for c in CONFIG_CASES], ids=[c[0] for c in CONFIG_CASES])
def test_hpgs_suggest_on_a_broken_config_yml_is_one_line(tmp_path, monkeypatch, config_text, make, says):
    config = tmp_path / "config.yml"
    config.write_bytes(make(config_text).encode("latin-1"))
    line = hpgs_error(monkeypatch, "suggest", "--load-config", config)
    assert line.startswith(f"{config} {says}") and line.endswith("(outputs/<experiment>/<method>/<timestamp>/)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.yml"]  # no suggestions written


def test_hpgs_suggest_on_a_run_folder_says_to_pass_its_config_yml(tmp_path, monkeypatch, config_text):
    (tmp_path / "config.yml").write_text(config_text)
    assert hpgs_error(monkeypatch, "suggest", "--load-config", tmp_path) == (
        f"--load-config {tmp_path} is a run folder; pass its config.yml: --load-config {tmp_path / 'config.yml'}")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert hpgs_error(monkeypatch, "suggest", "--load-config", empty).startswith(
        f"--load-config {empty} is a folder, not a run's config.yml")


@pytest.mark.parametrize("make", [c[1] for c in CONFIG_CASES[1:3]], ids=[c[0] for c in CONFIG_CASES[1:3]])
def test_ns_eval_on_a_file_that_names_no_plugin_class_keeps_nerfstudios_traceback(tmp_path, monkeypatch, make,
                                                                                 config_text):
    """Not the plugin's run (no `hpgs_ns.` class in it): the hook hands the exception on as it came."""
    from nerfstudio.utils.eval_utils import eval_setup

    import hpgs_ns.method_config  # noqa: F401

    config = tmp_path / "config.yml"
    config.write_text(make(config_text))
    monkeypatch.setattr(sys, "argv", ["ns-eval", "--load-config", str(config)])
    with pytest.raises(Exception) as info:  # noqa: B017 (nerfstudio's own)
        eval_setup(config)
    fallen = []
    print_user_errors(type(info.value), info.value, info.value.__traceback__, lambda *a: fallen.append(a[1]))
    assert fallen == [info.value]


@pytest.mark.parametrize("make,says", [c[1:] for c in CONFIG_CASES[:1]], ids=[c[0] for c in CONFIG_CASES[:1]])
def test_ns_eval_and_ns_viewer_on_a_broken_config_yml_print_one_line(tmp_path, monkeypatch, config_text, make, says):
    """nerfstudio's `eval_setup` (what ns-eval and ns-viewer call) fails on the file; the excepthook the plugin
    installs re-reads --load-config and prints what is wrong with it."""
    from nerfstudio.utils.eval_utils import eval_setup

    import hpgs_ns.method_config  # noqa: F401 (what nerfstudio imports: it installs the hook and its explainer)

    config = tmp_path / "config.yml"
    config.write_text(make(config_text))
    monkeypatch.setattr(sys, "argv", ["ns-eval", "--load-config", str(config), "--output-path", str(tmp_path / "o.json")])
    with pytest.raises(Exception) as info:  # noqa: B017 (nerfstudio's own: yaml's, AssertionError, AttributeError)
        eval_setup(config)
    assert not isinstance(info.value, UserError)
    assert one_line(info.value).startswith(f"{config} {says}")
    # an exception raised outside eval_setup, without --load-config, keeps its traceback
    monkeypatch.setattr(sys, "argv", ["ns-eval"])
    fallen = []
    try:
        raise RuntimeError("unrelated")
    except RuntimeError as err:
        other = err
    print_user_errors(RuntimeError, other, other.__traceback__, lambda *a: fallen.append(a[0]))
    assert fallen == [RuntimeError]


def test_read_run_config_reads_old_and_new_configs(config_text, tmp_path):
    for old in ("run-0.1.0", "run-0.2.0"):
        assert read_run_config(REPO / "tests" / "data" / old / "config.yml").method_name == "hpgs"
    (tmp_path / "config.yml").write_text(config_text)
    assert read_run_config(tmp_path / "config.yml").max_num_iterations == 100
    with pytest.raises(RunConfigError, match="nope.yml not found; pass --load-config RUN/config.yml"):
        read_run_config(tmp_path / "nope.yml")


# ---- selected_views.json, checkpoints, preference models, bench results ---------------------------------------

ROUND_LOG = {"selector": "random", "initial": ["images/0001.png"], "active": ["images/0001.png", "images/0002.png"],
             "withheld": [], "test": ["images/0000.png"],
             "rounds": [{"round": 1, "step": 10, "selector": "random", "chosen": ["images/0002.png"], "chosen_indices": [1],
                         "seconds": 0.1, "num_active": 2}]}

ROUND_LOG_CASES = [
    ("truncated", lambda: json.dumps(ROUND_LOG)[:50], "is not readable JSON (JSONDecodeError"),
    ("a list", lambda: "[]", "is not a round log (TypeError: no list of rounds)"),
    ("rounds not a list", lambda: json.dumps({**ROUND_LOG, "rounds": 3}), "is not a round log"),
    ("a round without a step", lambda: json.dumps({**ROUND_LOG, "rounds": [{"round": 1}]}), "is not a round log (KeyError"),
    ("a step that is not a number", lambda: json.dumps({**ROUND_LOG, "rounds": [{**ROUND_LOG["rounds"][0], "step": "x"}]}),
     "is not a round log (ValueError"),
    ("active not names", lambda: json.dumps({**ROUND_LOG, "active": [1]}),
     "is not a round log (TypeError: active is not a list of view names)"),
]


@pytest.mark.parametrize("make,says", [c[1:] for c in ROUND_LOG_CASES], ids=[c[0] for c in ROUND_LOG_CASES])
def test_a_broken_round_log_is_one_line(tmp_path, make, says):
    path = tmp_path / "selected_views.json"
    path.write_text(make())
    with pytest.raises(RoundLogError) as info:
        SelectionLog.read(path)
    line = one_line(info.value)
    assert line.startswith(f"{path} {says}") and line.endswith("re-run the training (a finished run writes it), or "
                                                               "restore it from a copy")
    path.write_text(json.dumps(ROUND_LOG))
    log = SelectionLog.read(path)
    assert [r.to_dict() for r in log.rounds] == [{**r, "test_psnr_before": None, "reset": False, "scores": {},
                                                  "work": {}} for r in ROUND_LOG["rounds"]]
    assert (log.version, log.selector, log.seed, log.test, log.stopped) == (2, "random", 0, ["images/0000.png"], None)
    assert (log.initial, log.active, log.chosen) == (ROUND_LOG["initial"], ROUND_LOG["active"], ["images/0002.png"])


CHECKPOINT_CASES = [
    ("step not a number", {"step": "x", "pipeline": {}, "optimizers": {}}, "is not a nerfstudio checkpoint (its step"),
    ("pipeline not a dict", {"step": 3, "pipeline": [1], "optimizers": {}}, "is not a nerfstudio checkpoint (its step"),
    ("no optimizers", {"step": 3, "pipeline": {}}, "is not a nerfstudio checkpoint (no step, pipeline and optimizers)"),
    ("not a dict", [1, 2], "is not a nerfstudio checkpoint"),
]


@pytest.mark.parametrize("state,says", [c[1:] for c in CHECKPOINT_CASES], ids=[c[0] for c in CHECKPOINT_CASES])
def test_a_checkpoint_with_wrong_typed_fields_is_one_line(tmp_path, state, says):
    path = tmp_path / "step-000000003.ckpt"
    torch.save(state, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint_file(path)
    assert one_line(info.value).startswith(f"{path} {says}")


PREFERENCE_CASES = [
    ("input size a string", lambda c: c["input_recipe"].update(resize_short_side="64"), "its recipe: TypeError"),
    ("no recipe", lambda c: c.pop("input_recipe"), "its recipe: KeyError"),
    ("head of the wrong shape", lambda c: c["head"].update(weight=torch.zeros(3)), "weights do not fit the alexnet model"),
    ("feature mean a list", lambda c: c.update(feature_mean=[1.0]), "weights do not fit the alexnet model"),
    ("meta a list", lambda c: c.update(meta=[1]), "not an hpgs preference-model checkpoint (meta is a list)"),
]


@pytest.mark.parametrize("change,says", [c[1:] for c in PREFERENCE_CASES], ids=[c[0] for c in PREFERENCE_CASES])
def test_a_preference_model_with_wrong_typed_fields_is_one_line(tmp_path, light_preference_model, change, says):
    checkpoint = torch.load(light_preference_model, map_location="cpu", weights_only=True)
    change(checkpoint)
    path = tmp_path / "model.pt"
    torch.save(checkpoint, path)
    with pytest.raises(PreferenceModelError) as info:
        PreferenceModel.load(path)
    assert one_line(info.value).startswith(f"{path}: ") and says in str(info.value)


def test_hpgs_label_on_a_latin1_csv_is_one_line(pairs_folder):
    from hpgs_ns.preference.label_server import LabelBook
    from hpgs_ns.preference.pairs import PairsError

    csv_path = pairs_folder / "pairs.csv"
    csv_path.write_bytes(PAIRS_CASES[0][1])
    with pytest.raises(PairsError) as info:
        LabelBook(csv_path)
    assert one_line(info.value).startswith(f"{csv_path}: not UTF-8 text (byte 0xe9")
    assert csv_path.read_bytes() == PAIRS_CASES[0][1]  # left as it was


def test_a_wrong_sized_first_photo_at_full_resolution_names_no_rounding(colmap_scene, tmp_path):
    import shutil

    scene = Path(shutil.copytree(colmap_scene, tmp_path / "scene"))
    photo = scene / "images" / "0001.png"  # the first training view: checked when the split is parsed
    with Image.open(photo) as image:
        image.resize((20, 14)).save(photo)
    with pytest.raises(SceneDataError) as info:
        MipNerf360DataParserConfig(data=scene, downscale_factor=1).setup().get_dataparser_outputs("train")
    assert one_line(info.value) == (f"{photo} is 20x14 but its camera says 32x24; replace it with the 32x24 photo its "
                                    f"camera was made from, or remove it from the COLMAP model ({scene / 'sparse' / '0'})")
