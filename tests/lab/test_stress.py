"""Stress mode: the perturbed scene copies, the dataparser dropping unreadable frames, and the stress table."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import run_training, short_config
from helpers import make_result, text_copy
from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils
from PIL import Image

from hpgs_lab.report import stress_table
from hpgs_lab.results import RunResult
from hpgs_lab.stress import Corrupt, Exposure, PoseNoise, StressConfig, perturbed_copy, split_names
from hpgs_ns.dataparser import MipNerf360DataParserConfig, SceneDataError, _make_downscaled_folder
from hpgs_ns.errors import UserError
from hpgs_ns.image_files import image_problem
from hpgs_ns.scenes.colmap_model import read_images


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A 40-camera, 64x48 `ring` scene with an `images_2/` folder (35 training, 5 test views)."""
    from hpgs_ns.scenes.synthetic import make_scene

    path = make_scene(
        tmp_path_factory.mktemp("stress") / "ring", layout="ring", num_cameras=40, width=64, height=48, num_points=1500, seed=0
    )
    (path / "images_2").mkdir()
    for image in sorted((path / "images").iterdir()):
        Image.open(image).resize((32, 24)).save(path / "images_2" / image.name)
    return path


def digest(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): hashlib.sha1(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def poses(scene: Path) -> dict:
    """name -> (world-from-camera rotation [3, 3], camera centre [3])."""
    out = {}
    for im in colmap_utils.read_images_binary(scene / "sparse" / "0" / "images.bin").values():
        r = colmap_utils.qvec2rotmat(im.qvec)
        out[im.name] = (r.T, -r.T @ im.tvec)
    return out


def parse(scene: Path, **config):
    parser = MipNerf360DataParserConfig(data=scene, **config).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    return [p.name for p in train.image_filenames], [p.name for p in test.image_filenames]


def test_split_names_is_every_8th_in_file_name_order(scene):
    train, test = split_names(scene)
    assert test == ["0000.png", "0008.png", "0016.png", "0024.png", "0032.png"] and len(train) == 35
    assert (train, test) == parse(scene)


def test_pose_noise_moves_training_poses_by_about_the_requested_amount(scene, tmp_path):
    before = digest(scene)
    config = StressConfig(pose_noise=PoseNoise(translation=0.05, rotation_deg=2.0))
    copy = perturbed_copy(scene, "pose-noise", tmp_path, config)
    assert copy == tmp_path / "ring+pose-noise"
    old, new = poses(scene), poses(copy)
    train, test = split_names(scene)
    for name in test:  # test views keep their exact poses
        assert np.array_equal(old[name][0], new[name][0]) and np.array_equal(old[name][1], new[name][1])
    centres = np.stack([c for _, c in old.values()])
    spread = math.sqrt(((centres - centres.mean(0)) ** 2).sum(1).mean())
    angles = [math.degrees(math.acos(np.clip((np.trace(new[n][0] @ old[n][0].T) - 1) / 2, -1, 1))) for n in train]
    shifts = [np.linalg.norm(new[n][1] - old[n][1]) / spread for n in train]
    rms = lambda v: math.sqrt(sum(x * x for x in v) / len(v))  # noqa: E731
    # 35 draws of a 3D Gaussian: the RMS is within 30% of its expectation with probability > 0.999.
    assert 0.7 * 2.0 < rms(angles) < 1.3 * 2.0 and min(angles) > 0
    assert 0.7 * 0.05 < rms(shifts) < 1.3 * 0.05 and min(shifts) > 0
    report = json.loads((copy / "stress.json").read_text())["report"]
    assert report["rms_rotation_deg"] == pytest.approx(rms(angles), rel=1e-3)
    assert report["camera_spread"] == pytest.approx(spread, rel=1e-6)
    # Images and 3D points are untouched, and so is the source scene.
    images = lambda d: {k: v for k, v in d.items() if k.startswith("images")}  # noqa: E731
    assert images(digest(copy)) == images(before)
    points = lambda s: {k: p.xyz.tolist() for k, p in colmap_utils.read_points3D_binary(s / "sparse/0/points3D.bin").items()}  # noqa: E731
    assert points(copy) == points(scene)
    assert digest(scene) == before


def test_exposure_changes_only_training_images_by_the_recorded_gain_and_gamma(scene, tmp_path):
    before = digest(scene)
    copy = perturbed_copy(scene, "exposure", tmp_path)
    after = digest(copy)
    train, test = split_names(scene)
    for folder in ("images", "images_2"):
        assert all(after[f"{folder}/{n}"] == before[f"{folder}/{n}"] for n in test)
        assert all(after[f"{folder}/{n}"] != before[f"{folder}/{n}"] for n in train)
    views = json.loads((copy / "stress.json").read_text())["report"]["views"]
    assert sorted(views) == sorted(train)
    gains = [v["gain"] for v in views.values()]
    assert 0.6 <= min(gains) and max(gains) <= 1.4 and max(gains) - min(gains) > 0.4
    assert all(0.8 <= v["gamma"] <= 1.25 for v in views.values())
    name = train[0]
    src = np.asarray(Image.open(scene / "images" / name).convert("RGB")) / 255.0
    out = np.asarray(Image.open(copy / "images" / name).convert("RGB")) / 255.0
    expect = np.clip(views[name]["gain"] * src ** views[name]["gamma"], 0, 1)
    assert np.abs(out - expect).max() <= 0.5 / 255 + 1e-9  # PNG: exact up to rounding
    assert sorted(json.loads((copy / "stress.json").read_text())["params"]["strength"]) == ["gain", "gamma"]
    assert digest(scene) == before  # hard-linked files were replaced, never written into


def test_corrupt_makes_training_files_unreadable_in_every_resolution(scene, tmp_path):
    before = digest(scene)
    copy = perturbed_copy(scene, "corrupt", tmp_path, StressConfig(corrupt=Corrupt(count=3)))
    views = json.loads((copy / "stress.json").read_text())["report"]["views"]
    train, _ = split_names(scene)
    assert len(views) == 3 and set(views) <= set(train) and sorted(views.values()) == ["empty", "truncated", "truncated"]
    for folder in ("images", "images_2"):
        bad = {p.name for p in (copy / folder).iterdir() if image_problem(p) is not None}
        assert bad == set(views)
    assert all((copy / "images" / n).stat().st_size == 0 for n, kind in views.items() if kind == "empty")
    assert digest(scene) == before and all(image_problem(p) is None for p in (scene / "images").iterdir())


def test_copies_are_reused_rebuilt_on_new_strength_and_seeded(scene, tmp_path):
    first = perturbed_copy(scene, "exposure", tmp_path / "a")
    stamp = (first / "stress.json").stat().st_mtime_ns
    assert perturbed_copy(scene, "exposure", tmp_path / "a") == first and (first / "stress.json").stat().st_mtime_ns == stamp
    again = perturbed_copy(scene, "exposure", tmp_path / "b")
    assert digest(again) == digest(first)  # same seed, same bytes
    other = perturbed_copy(scene, "exposure", tmp_path / "c", StressConfig(seed=1))
    assert digest(other)["images/0001.png"] != digest(first)["images/0001.png"]
    stronger = perturbed_copy(scene, "exposure", tmp_path / "a", StressConfig(exposure=Exposure(gain=(0.3, 0.4))))
    assert stronger == first and (first / "stress.json").stat().st_mtime_ns != stamp
    gains = [v["gain"] for v in json.loads((first / "stress.json").read_text())["report"]["views"].values()]
    assert max(gains) <= 0.4
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["ring+exposure"]  # no temp folders left


def test_dataparser_drops_unreadable_frames_once_and_keeps_the_test_split(scene, tmp_path, capsys):
    copy = perturbed_copy(scene, "corrupt", tmp_path)
    bad = sorted(json.loads((copy / "stress.json").read_text())["report"]["views"])
    clean_train, clean_test = parse(scene)
    capsys.readouterr()
    train, test = parse(copy)
    assert test == clean_test  # split made before dropping: no test view shifts
    assert train == [n for n in clean_train if n not in bad] and len(train) == 32
    warnings = [line for line in capsys.readouterr().out.splitlines() if "unreadable" in line]
    assert len(warnings) == 1 and all(n in warnings[0] for n in bad), warnings
    # The images_2 folder is what --downscale-factor 2 reads: the same frames are dropped there.
    assert parse(copy, downscale_factor=2) == (train, test)


def test_dataparser_too_many_unreadable_is_one_line_error(scene, tmp_path):
    copy = perturbed_copy(scene, "corrupt", tmp_path)
    with pytest.raises(SceneDataError) as err:
        parse(copy, max_unreadable_fraction=0.05)
    message = str(err.value)
    assert "\n" not in message and "3 unreadable images" in message and "max-unreadable-fraction" in message
    assert all(n in message for n in json.loads((copy / "stress.json").read_text())["report"]["views"])


def test_dataparser_error_when_every_test_view_is_unreadable(scene, tmp_path):
    copy = perturbed_copy(scene, "exposure", tmp_path)  # any private copy to damage
    _, test = split_names(copy)
    for name in test:
        target = copy / "images" / name
        target.unlink()  # a hard link: unlink, never truncate in place
        target.write_bytes(b"")
    with pytest.raises(SceneDataError, match="the test split would be empty"):
        parse(copy, max_unreadable_fraction=0.5)


def test_downscaling_a_corrupt_image_is_a_clear_error(scene, tmp_path):
    copy = perturbed_copy(scene, "corrupt", tmp_path)
    name = sorted(json.loads((copy / "stress.json").read_text())["report"]["views"])[0]
    with pytest.raises(SceneDataError, match=f"cannot read .*{name}"):
        _make_downscaled_folder(copy / "images", [copy / "images" / name], 4, "floor")
    assert not (copy / "images_4").exists() and not list(copy.glob(".images_4-*"))


def row(scene, selector, psnr, seed=0):
    return make_result(scene, "hpgs", selector, seed, psnr)


def test_stress_table_pairs_each_perturbed_run_with_the_same_seeds_clean_run():
    rows = [
        row("ring", "random", 20.0), row("ring", "random", 22.0, seed=1), row("ring", "random", 30.0, seed=2),
        row("ring+exposure", "random", 18.5), row("ring+exposure", "random", 19.5, seed=1),
        row("ring+pose-noise", "random", 17.0),
        row("ring", "fisher", 23.0), row("ring+exposure", "fisher", 22.75), row("ring", "all", 25.0),
        make_result("ring", "fisherrf", "random", 0, 21.0),  # a group with no perturbed run: no table
    ]
    table = stress_table(rows).splitlines()
    assert table[0].startswith("**ring / hpgs**")
    assert table[2] == "| selector | clean | exposure | pose-noise | mean change |"
    # clean over seeds 0-1 (seed 2 never ran perturbed); pose-noise ran seed 0 only: 17 - 20, not 17 - 21.
    assert table[4] == "| random | 21.00 | 19.00 (-2.00) | 17.00 (-3.00) | -2.50 |"
    assert table[5] == "| fisher | 23.00 | 22.75 (-0.25) | – | – |"  # no mean over a partial row
    assert table[6] == "| all | 25.00 | – | – | – |"
    assert not any("fisherrf" in line for line in table)
    assert stress_table([row("ring", "random", 20.0)]) == ""


def test_bench_stress_runs_each_scene_clean_and_perturbed(scene, tmp_path, monkeypatch):
    """`hpgs bench --stress` wiring, with training replaced by a stub that records which scene it was given."""
    from hpgs_lab import runs as bench_module

    def fake_run(bench, job, env=None, sweep=None) -> RunResult:
        parse(job.scene.path)  # the real dataparser must accept the perturbed copy
        psnr = 20.0 - 1.5 * ("+" in job.scene.name)
        return make_result(job.scene.name, job.protocol.name, job.name, job.seed, psnr, 0.5, 0.3, repeat=job.repeat,
                           data=str(job.scene.path), num_views_final=6)

    monkeypatch.setattr(bench_module, "run_one", fake_run)
    monkeypatch.setattr("hpgs_lab.report.make_plots", lambda rows, out: [])
    out = tmp_path / "bench"
    bench_module.Bench(scenes=[scene], out=out, selectors=["random"], seeds=[0], references=False, stress=["corrupt", "exposure"]).main()
    assert sorted(p.relative_to(out).as_posix() for p in out.glob("*/*/*/seed*.json")) == [
        "ring+corrupt/hpgs/random/seed0.json", "ring+exposure/hpgs/random/seed0.json", "ring/hpgs/random/seed0.json",
    ]
    assert sorted(p.name for p in (out / "_scenes").iterdir()) == ["ring+corrupt", "ring+exposure"]
    assert "| random | 20.00 | 18.50 (-1.50) | 18.50 (-1.50) | -1.50 |" in (out / "stress.md").read_text()
    written = RunResult.from_json(out / "ring+exposure/hpgs/random/seed0.json")
    assert (written.scene, written.test.psnr, written.num_views_final) == ("ring+exposure", 18.5, 6)
    assert written.data == str(out.resolve() / "_scenes" / "ring+exposure")
    assert (out / "ring-hpgs-stress.png").stat().st_size > 5_000
    with pytest.raises(UserError, match="not a scene folder"):
        bench_module.Bench(scenes=[tmp_path], out=out, stress=["corrupt"]).main()


def test_training_runs_on_a_corrupt_copy(scene, tmp_path):
    """The real datamanager and trainer on the corrupt copy: the dropped frames are neither trained on nor tested."""

    copy = perturbed_copy(scene, "corrupt", tmp_path)
    bad = set(json.loads((copy / "stress.json").read_text())["report"]["views"])
    trainer = run_training(short_config(copy, tmp_path / "runs", steps=6, every=3, rounds=1, initial=4))
    dm = trainer.pipeline.datamanager
    assert len(dm.image_names) == 32 and not bad & {Path(n).name for n in dm.image_names} and len(dm.active) == 5
    assert [Path(p).name for p in dm.eval_dataset.image_filenames] == split_names(scene)[1]


def test_pose_noise_on_a_text_model_rewrites_text_and_keeps_test_poses(scene, tmp_path):
    text = text_copy(scene, tmp_path / "ring-text")
    copy = perturbed_copy(text, "pose-noise", tmp_path / "out", StressConfig(pose_noise=PoseNoise(translation=0.05, rotation_deg=2.0)))
    model = copy / "sparse" / "0"
    assert sorted(p.name for p in model.iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]
    old = {im.name: im for im in read_images(text / "sparse" / "0").values()}
    new = {im.name: im for im in read_images(model).values()}
    train, test = split_names(text)
    for name in test:
        assert np.array_equal(old[name].qvec, new[name].qvec) and np.array_equal(old[name].tvec, new[name].tvec)
    centre = lambda im: -colmap_utils.qvec2rotmat(im.qvec).T @ im.tvec  # noqa: E731
    moved = [np.linalg.norm(centre(new[n]) - centre(old[n])) for n in train]
    assert min(moved) > 0
