"""benchmarks/triangulation_variants.py, the triangulation variants `triangulation_yield.py` tried and the plugin
does not ship: guided matching's every-pair epipolar distance and its matches. (The shipped triangulation:
tests/plugin/test_triangulate.py.)"""

from __future__ import annotations

import importlib
import sys

import numpy as np
import pytest
import torch
from conftest import REPO

from hpgs_ns.scenes.triangulate import colmap_cam_from_world, colmap_camera_model, epipolar_distance, relative_pose


@pytest.fixture(scope="module")
def variants():
    """The script as a module (its dataclasses need it in sys.modules, hence an import from benchmarks/)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        yield importlib.import_module("triangulation_variants")
    finally:
        sys.path.remove(str(REPO / "benchmarks"))


def look_at_cameras(num: int, width: int = 320, height: int = 240, **kwargs):
    """`num` nerfstudio cameras on a ring of radius 3 looking at the origin (OpenGL: z points back, away from it)."""
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
    import pycolmap

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


def test_guided_matching_keeps_mutual_nearest_descriptors_within_the_epipolar_band(variants):
    """Guided matching: its every-pair epipolar distance agrees with the package's on matched points, and only
    candidates within the band compete."""
    colmap_cameras, cam2_from_cam1, pixels = two_views_of_points()
    every = variants.epipolar_distance_matrix(*colmap_cameras, cam2_from_cam1, pixels[0], pixels[1])
    distance = epipolar_distance(*colmap_cameras, cam2_from_cam1, pixels[0], pixels[1])
    assert every.shape == (50, 50) and np.allclose(np.diag(every), distance, atol=1e-6)  # the diagonal: true matches
    rng = np.random.default_rng(1)
    descriptors = rng.integers(0, 255, (50, 128)).astype(np.uint8)
    noisy = np.clip(descriptors + rng.integers(-20, 20, (50, 128)), 0, 255).astype(np.uint8)
    matches = variants.guided_matches(descriptors, noisy, every, max_error=4.0, max_ratio=0.9)
    assert len(matches) >= 45 and (matches[:, 0] == matches[:, 1]).all()
    assert len(variants.guided_matches(descriptors, noisy, np.full((50, 50), np.inf), 4.0, 0.9)) == 0  # no band, no match
    assert variants.VariantSettings(verification="guided").verification == "guided"
