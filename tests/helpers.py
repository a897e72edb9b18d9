"""Helpers the test files share (importable as `helpers` from tests/plugin and tests/lab: pytest puts tests/, the
folder of the top conftest.py, on sys.path): one-line errors as `hpgs` prints them, and the lab's rows
(`RunResult`s with given numbers, and a results folder of them)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from PIL import Image

from hpgs_ns.errors import print_user_errors

if TYPE_CHECKING:  # the plugin's tests never import the lab
    from hpgs_lab.results import RunResult


def one_line(err: BaseException) -> str:
    """What the excepthook prints for `err` (asserting it is one `error: ...` line), without the `error: `."""
    printed = []
    fallback = lambda *args: pytest.fail(f"not a one-line error: {args[0].__name__}: {args[1]}")  # noqa: E731

    class Err:
        @staticmethod
        def write(text):
            printed.append(text)

    real, sys.stderr = sys.stderr, Err
    try:
        print_user_errors(type(err), err, err.__traceback__, fallback)
    finally:
        sys.stderr = real
    text = "".join(printed)
    assert text.startswith("error: ") and text.endswith("\n") and text.count("\n") == 1, text
    return text[len("error: "):-1]


def hpgs_error(monkeypatch, *args: str) -> str:
    """Run `hpgs ARGS` in-process; it must fail as a one-line error. Returns the line."""
    from hpgs_ns.cli import entrypoint

    monkeypatch.setattr(sys, "argv", ["hpgs", *map(str, args)])
    with pytest.raises(Exception) as info:  # noqa: B017 (any exception: one_line says whether it prints as one line)
        entrypoint()
    return one_line(info.value)


def make_result(scene="s", protocol="hpgs", selector="random", seed=0, psnr=20.0, ssim=0.5, lpips=0.3, *,
                wall=1.0, selection=0.0, device="cpu x2", runs_per_gpu=1, sweep_id=None, started_at=None,
                settings=None, gpu=None, mps=None, **fields) -> RunResult:
    """A run with the given numbers (the lab's test files build their rows with this)."""
    from hpgs_lab.results import Metrics, Provenance, RunResult, Timing

    return RunResult(scene=scene, protocol=protocol, selector=selector, seed=seed, test=Metrics(psnr, ssim, lpips),
                     timing=Timing(wall, selection, sweep_id=sweep_id, started_at=started_at, runs_per_gpu=runs_per_gpu,
                                   gpu=gpu, mps=mps),
                     provenance=Provenance(device=device, settings=settings), **fields)


def write_rows(out, data) -> None:
    """Write `data` (RunResults) under `out` as `hpgs bench` lays a results folder out."""
    for r in data:
        r.to_json(out / r.scene / r.protocol / r.selector / f"seed{r.seed}.json")


def lab_commands_env() -> dict:
    """The environment that registers the lab's `hpgs` commands in a subprocess as pyproject.toml declares them
    (`$HPGS_COMMANDS`: this checkout is on PYTHONPATH, but the venv's installed metadata may be another's)."""
    from pathlib import Path

    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    commands = pyproject["project"]["entry-points"]["hpgs.commands"]
    return {"HPGS_COMMANDS": ",".join(f"{name}={spec}" for name, spec in commands.items())}


def make_capture(folder: Path, frames: int = 6) -> Path:
    """A tiny transforms.json capture (32x24 PNGs)."""
    (folder / "images").mkdir(parents=True)
    entries = []
    for i in range(frames):
        Image.new("RGB", (32, 24), (40 * i, 80, 120)).save(folder / "images" / f"{i:04d}.png")
        entries.append({"file_path": f"images/{i:04d}.png",
                        "transform_matrix": [[1, 0, 0, i * 0.1], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]})
    meta = {"fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 12.0, "w": 32, "h": 24, "frames": entries}
    (folder / "transforms.json").write_text(json.dumps(meta, indent=1))
    return folder


def text_copy(scene: Path, dest: Path) -> Path:
    """The scene with its model converted to COLMAP's text format (and no rig/frame files)."""
    import shutil

    from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils

    shutil.copytree(scene, dest)
    model = dest / "sparse" / "0"
    cameras, images, points = colmap_utils.read_model(model, ".bin")
    for path in model.iterdir():
        path.unlink()
    colmap_utils.write_model(cameras, images, points, model, ext=".txt")
    return dest


def train_steps(trainer, steps) -> None:
    """Run trainer steps as nerfstudio's loop does: the callbacks before each iteration, the iteration, the callbacks
    after (a selection round, densification and the model's step bookkeeping run in them)."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation as At

    for step in steps:
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, location=At.BEFORE_TRAIN_ITERATION)
        trainer.train_iteration(step)
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, location=At.AFTER_TRAIN_ITERATION)


def load_script(path):
    """A script outside the packages (benchmarks/, scripts/) as a module, to test its functions. It is in
    sys.modules under its name while it runs and after (its dataclasses look their module up there)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


# ---- cameras for the triangulation's tests (tests/plugin/test_triangulate.py, tests/lab/test_triangulation_variants.py)

def look_at_cameras(num: int, width: int = 320, height: int = 240, **kwargs):
    """`num` nerfstudio cameras on a ring of radius 3 looking at the origin (OpenGL: z points back, away from it)."""
    import numpy as np
    import torch
    from nerfstudio.cameras.cameras import Cameras

    c2ws = []
    for k in range(num):
        angle = 2 * np.pi * k / num
        centre = np.array([3 * np.cos(angle), 3 * np.sin(angle), 0.8])
        back = centre / np.linalg.norm(centre)
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        c2ws.append(np.stack([right, np.cross(back, right), back, centre], 1))
    return Cameras(camera_to_worlds=torch.tensor(np.array(c2ws), dtype=torch.float32), fx=250.0, fy=240.0,
                   cx=width / 2 + 3.5, cy=height / 2 - 2.0, width=width, height=height, **kwargs)


def two_views_of_points(num: int = 50):
    """(pycolmap cameras [2], cam2_from_cam1, pixels [2] of [num, 2]): `num` random 3D points seen by two distorted
    views 45 degrees apart on the ring."""
    import numpy as np
    import pycolmap
    import torch

    from hpgs_ns.scenes.triangulate import colmap_cam_from_world, colmap_camera_model, relative_pose

    cameras = look_at_cameras(8, distortion_params=torch.tensor([[0.05, -0.02, 0.0, 0.0, 0.001, -0.002]] * 8))
    a, b = 0, 1
    points = np.random.default_rng(0).uniform(-0.6, 0.6, (num, 3))
    pixels, colmap_cameras = [], []
    for i in (a, b):
        model, width, height, params = colmap_camera_model(cameras, i)
        colmap_cameras.append(pycolmap.Camera(model=model, width=width, height=height, params=params))
        cam_from_world = pycolmap.Rigid3d(colmap_cam_from_world(cameras.camera_to_worlds[i]))
        pixels.append(np.stack([colmap_cameras[-1].img_from_cam(cam_from_world * p) for p in points]))
    return colmap_cameras, relative_pose(cameras.camera_to_worlds[a], cameras.camera_to_worlds[b]), pixels
