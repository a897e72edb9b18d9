"""Property-based tests of every plugin reader (#44): a valid file truncated, with bytes flipped, or with a field
given a value of another type, reads as a valid file or fails with the reader's one-line `UserError` naming the
file: never another exception (a `struct.error`, `UnicodeDecodeError`, `KeyError`, ...). (The lab's readers, a
suite TOML and a benchmark result: tests/lab/test_fuzz_lab_readers.py; the generators: tests/fuzzing.py.)
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from fuzzing import OTHER_VALUES, damaged, fuzz, json_variants, reads_or_one_line
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

# ---- COLMAP models --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def colmap_model(tmp_path_factory) -> Path:
    from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils

    from hpgs_ns.scenes.colmap_model import read_model_file
    from hpgs_ns.scenes.synthetic import make_scene

    scene = make_scene(tmp_path_factory.mktemp("fuzz-colmap") / "scene", layout="ring", num_cameras=8, width=32,
                       height=24, num_points=40, seed=0)
    model = scene / "sparse" / "0"
    for stem, write in (("cameras", colmap_utils.write_cameras_text), ("images", colmap_utils.write_images_text),
                        ("points3D", colmap_utils.write_points3D_text)):
        write(read_model_file(model / f"{stem}.bin"), model / f"{stem}.txt")
    return model


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt"])
def test_damaged_colmap_model_files_read_or_fail_in_one_line(colmap_model, tmp_path, name):
    from hpgs_ns.scenes.colmap_model import ColmapModelError, read_model_file

    original = (colmap_model / name).read_bytes()
    path = tmp_path / name

    @fuzz(40)
    @given(damaged(original))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: read_model_file(path), path, ColmapModelError)

    check()


# ---- transforms.json ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-capture")
    (folder / "images").mkdir()
    frames = []
    for i in range(5):
        Image.new("RGB", (16, 12), (40 * i, 80, 120)).save(folder / "images" / f"{i:04d}.png")
        frames.append({"file_path": f"images/{i:04d}.png",
                       "transform_matrix": [[1, 0, 0, i * 0.1], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]})
    meta = {"fl_x": 15.0, "fl_y": 15.0, "cx": 8.0, "cy": 6.0, "w": 16, "h": 12, "k1": 0.0, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_transforms_json_with_a_retyped_field_or_damaged_bytes_reads_or_fails_in_one_line(capture, tmp_path):
    from hpgs_ns.dataparser import HpgsNerfstudioDataParserConfig, SceneDataError

    folder = tmp_path / "capture"
    shutil.copytree(capture, folder)
    path = folder / "transforms.json"
    original = json.loads((capture / "transforms.json").read_text())

    @fuzz(60)
    @given(json_variants(original))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: HpgsNerfstudioDataParserConfig(data=folder).setup().get_dataparser_outputs("train"),
                          path, SceneDataError)

    check()


# ---- pairs CSVs, images ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pairs_csv(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-pairs")
    for i in range(3):
        Image.new("RGB", (8, 8), (80 * i, 0, 0)).save(folder / f"{i}.png")
    path = folder / "pairs.csv"
    path.write_text("Image_1,Image_2,Human Preference,Skipped\n0.png,1.png,1,\n1.png,2.png,0,\n0.png,2.png,,1\n")
    return path


def test_damaged_pairs_csvs_read_or_fail_in_one_line(pairs_csv):
    from hpgs_ns.preference.pairs import PairsError, read_usable_pairs

    original = pairs_csv.read_bytes()
    path = pairs_csv.parent / "damaged.csv"

    @fuzz(80)
    @given(damaged(original))
    def check(data):
        path.write_bytes(data)
        try:
            read_usable_pairs([path])
        except PairsError as err:
            # names the CSV, or the image a (damaged) row names
            assert "\n" not in str(err) and str(path.parent) in str(err), str(err)

    check()


def test_damaged_images_read_or_fail_in_one_line(pairs_csv):
    from hpgs_ns.preference.pairs import PairsError, check_image, load_image

    original = (pairs_csv.parent / "0.png").read_bytes()
    path = pairs_csv.parent / "damaged.png"

    @fuzz(40)
    @given(damaged(original))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: check_image(path), path, PairsError)
        reads_or_one_line(lambda: load_image(path), path, PairsError)

    check()


# ---- a run's config.yml ---------------------------------------------------------------------------------------


def test_damaged_config_ymls_read_or_fail_in_one_line(tmp_path):
    from hpgs_ns.method_config import hpgs_trainer_config
    from hpgs_ns.run_config import RunConfigError, read_run_config

    original = yaml.dump(hpgs_trainer_config(100)).encode()
    path = tmp_path / "config.yml"

    @fuzz(40)
    @given(damaged(original))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: read_run_config(path), path, RunConfigError)

    check()


# ---- selected_views.json --------------------------------------------------------------------------------------

ROUND_LOG = {"selector": "random", "seed": 0, "initial": ["images/0001.png"], "active": ["images/0001.png", "images/0002.png"],
             "withheld": ["images/0003.png"], "test": ["images/0000.png"],
             "rounds": [{"round": 1, "step": 10, "selector": "random", "chosen": ["images/0002.png"], "chosen_indices": [1],
                         "seconds": 0.1, "num_active": 2, "scores": {"images/0002.png": 1.0}, "work": {"renders": 2.0}}]}


def test_damaged_round_logs_read_or_fail_in_one_line(tmp_path):
    from hpgs_ns.selection.log import RoundLogError, SelectionLog

    path = tmp_path / "selected_views.json"

    @fuzz(60)
    @given(json_variants(ROUND_LOG))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: SelectionLog.read(path), path, RoundLogError)

    check()


# ---- checkpoints and preference models ------------------------------------------------------------------------


def test_damaged_checkpoints_read_or_fail_in_one_line(tmp_path):
    from hpgs_ns.trainer import CheckpointError, load_checkpoint_file

    source = tmp_path / "source.ckpt"
    torch.save({"step": 3, "pipeline": {"_model.gauss_params.means": torch.zeros(4, 3)},
                "optimizers": {"means": {"state": {}, "param_groups": [{"lr": 1e-3, "params": [0]}]}},
                "schedulers": {}, "scalers": {}}, source)
    original = source.read_bytes()
    path = tmp_path / "step-000000003.ckpt"

    @fuzz(40)
    @given(damaged(original))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: load_checkpoint_file(path), path, CheckpointError)

    check()


def test_preference_models_with_retyped_fields_or_damaged_bytes_load_or_fail_in_one_line(light_preference_model, tmp_path):
    from hpgs_ns.preference.model import PreferenceModel
    from hpgs_ns.preference.recipe import PreferenceModelError

    original = light_preference_model.read_bytes()
    checkpoint = torch.load(light_preference_model, map_location="cpu", weights_only=True)
    fields = sorted(k for k in checkpoint if k != "backbone_state")
    path = tmp_path / "model.pt"

    def retype(choice) -> bytes:
        key, value = choice
        changed = dict(checkpoint, **{key: value})
        torch.save(changed, path)
        return path.read_bytes()

    @fuzz(25)
    @given(st.one_of(st.tuples(st.sampled_from(fields), OTHER_VALUES).map(retype), damaged(original)))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: PreferenceModel.load(path), path, PreferenceModelError)

    check()
