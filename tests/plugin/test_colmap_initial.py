"""`--pipeline.datamanager.seed-points colmap-initial`: the splat starts only from seed points that two initial views
see."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import short_config

from hpgs_ns.datamanager import ActiveViewError


def setup_trainer(scene, out, **dm):
    cfg = short_config(scene, out, steps=1, rounds=0, **dm)
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def test_colmap_initial_keeps_exactly_the_points_two_initial_views_see(tiny_scene, tmp_path):
    import pycolmap

    trainer = setup_trainer(tiny_scene, tmp_path, seed_points="colmap-initial")
    dm = trainer.pipeline.datamanager
    rec = pycolmap.Reconstruction(str(tiny_scene / "sparse" / "0"))
    initial = {im_id for im_id, im in rec.images.items() if f"images/{im.name}" in {dm.image_names[i] for i in dm.active}}
    assert len(initial) == 6
    seen = [len(initial & {e.image_id for e in p.track.elements}) for p in rec.points3D.values()]
    expected = sum(n >= 2 for n in seen)
    assert 0 < expected < len(seen)  # the filter has something to drop and something to keep
    assert trainer.pipeline.model.num_points == expected
    assert setup_trainer(tiny_scene, tmp_path / "loose").pipeline.model.num_points == len(seen)


def without_tracks(scene, out):
    """A copy of `scene` whose points3D.bin keeps every point but no track (like the bonsai-device copy)."""
    from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils

    copy = shutil.copytree(scene, out)
    path = copy / "sparse" / "0" / "points3D.bin"
    points = colmap_utils.read_points3D_binary(path)
    empty = np.zeros(0, dtype=np.int64)
    trackless = {k: p._replace(image_ids=empty, point2D_idxs=empty) for k, p in points.items()}
    colmap_utils.write_points3D_binary(trackless, path)
    return copy


def test_colmap_initial_without_tracks_names_the_model_and_the_fix(tiny_scene, tmp_path):
    scene = without_tracks(tiny_scene, tmp_path / "no-tracks")
    with pytest.raises(ActiveViewError, match=r"points3D has no point tracks .* use --pipeline.datamanager.seed-points active"):
        setup_trainer(scene, tmp_path / "run", seed_points="colmap-initial")


def test_colmap_initial_that_would_keep_nothing_says_so(tiny_scene, tmp_path):
    with pytest.raises(ActiveViewError, match=r"seed-points colmap-initial kept no seed point: .* use more initial views"):
        setup_trainer(tiny_scene, tmp_path, seed_points="colmap-initial", num_initial_views=1)
