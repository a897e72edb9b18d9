"""The COLMAP model helpers: format detection, and rewriting poses without touching the source or leaving stale
rig/frame poses behind."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from helpers import text_copy

from hpgs_ns.scenes.colmap_model import model_file, read_images, read_points3D, write_images


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    from hpgs_ns.scenes.synthetic import make_scene

    return make_scene(
        tmp_path_factory.mktemp("colmap") / "ring", layout="ring", num_cameras=16, width=32, height=24, num_points=300, seed=0
    )


def test_binary_is_preferred_and_missing_files_read_as_none(scene, tmp_path):
    model = scene / "sparse" / "0"
    assert model_file(model, "images") == model / "images.bin"
    assert model_file(tmp_path, "images") is None and read_images(tmp_path) is None and read_points3D(tmp_path) is None
    text = text_copy(scene, tmp_path / "text") / "sparse" / "0"
    assert model_file(text, "images") == text / "images.txt"
    binary, txt = read_images(model), read_images(text)
    assert sorted(binary) == sorted(txt) and all(np.allclose(binary[k].qvec, txt[k].qvec) for k in binary)
    xyz = lambda points: np.stack([p.xyz for p in points.values()])  # noqa: E731
    assert np.allclose(xyz(read_points3D(model)), xyz(read_points3D(text)))


def test_write_images_replaces_the_file_not_its_hard_links_and_drops_stale_rigs(scene, tmp_path):
    import pycolmap

    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    for path in (scene / "sparse" / "0").iterdir():
        os.link(path, model / path.name)  # as a stress copy links its source's files
    original = (scene / "sparse" / "0" / "images.bin").read_bytes()
    images = read_images(model)
    first = min(images)
    images[first] = images[first]._replace(tvec=images[first].tvec + np.array([0.5, 0.0, 0.0]))
    assert write_images(model, images) == model / "images.bin"
    assert (scene / "sparse" / "0" / "images.bin").read_bytes() == original  # the source is untouched
    assert sorted(p.name for p in model.iterdir()) == ["cameras.bin", "images.bin", "points3D.bin"]
    # COLMAP (pycolmap 4) rebuilds trivial rigs from the images and sees the new pose, not a stale frame pose.
    rec = pycolmap.Reconstruction(str(model))
    assert np.allclose(np.asarray(rec.images[first].cam_from_world().translation), images[first].tvec)
    assert rec.num_reg_images() == len(images)
