"""`--pipeline.datamanager.random-points views`: a splat without seed points starts from points on the active
views' pixel rays, coloured by their pixels, and draws them again from all active views when it restarts."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import run_training, short_config
from nerfstudio.cameras.cameras import Cameras, CameraType

from hpgs_ns.scenes.view_points import FAR, NEAR, axes_meeting_point, points_along_views


def look_at(centre: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """A nerfstudio camera-to-world [3, 4] at `centre` looking at `target` (the camera looks along -z, y up)."""
    back = torch.nn.functional.normalize(centre - target, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back), dim=0)
    up = torch.linalg.cross(back, right)
    return torch.stack([right, up, back, centre], dim=1)


TARGET = torch.tensor([0.3, -0.2, 0.1])
CENTRES = torch.tensor([[2.0, 0.0, 0.5], [0.0, 2.0, 0.8], [-2.0, 0.3, 0.2], [0.2, -2.0, 1.0]])


def cameras(centres: torch.Tensor, target: torch.Tensor = TARGET) -> Cameras:
    n = centres.shape[0]
    full = lambda value: torch.full((n, 1), value)  # noqa: E731
    return Cameras(camera_to_worlds=torch.stack([look_at(c, target) for c in centres]), fx=full(40.0), fy=full(40.0),
                   cx=full(32.0), cy=full(24.0), width=full(64), height=full(48), camera_type=CameraType.PERSPECTIVE)


def test_the_axes_meet_where_the_cameras_look():
    forwards = TARGET - CENTRES
    assert torch.allclose(axes_meeting_point(CENTRES, forwards), TARGET, atol=1e-5)
    # a forward-facing capture: parallel axes meet nowhere
    assert axes_meeting_point(CENTRES, torch.tensor([[1.0, 0.0, 0.0]]).expand(4, 3)) is None


def test_points_lie_on_their_views_rays_in_their_pixels_colours():
    cams = cameras(CENTRES)
    image = np.zeros((48, 64, 3), dtype=np.uint8)
    image[..., 0] = np.arange(64)[None, :] * 3  # red encodes the column, green the row
    image[..., 1] = np.arange(48)[:, None] * 5
    xyz, rgb = points_along_views(cams, lambda view: image, [0, 2], 1000, torch.Generator().manual_seed(0))
    assert xyz.shape == (1000, 3) and rgb.dtype == torch.uint8
    for view, rows in ((0, slice(0, 500)), (2, slice(500, 1000))):  # 500 from each view, in order
        c2w = cams.camera_to_worlds[view]
        local = (xyz[rows] - c2w[:, 3]) @ c2w[:, :3]  # camera frame: x right, y up, looking along -z
        depth = -local[:, 2]
        assert (depth > 0).all()
        u = 40.0 * local[:, 0] / depth + 32.0
        v = -40.0 * local[:, 1] / depth + 24.0
        column, row = u.floor().long(), v.floor().long()  # the pixel each point projects into
        assert torch.equal(rgb[rows, 0], torch.from_numpy(image[row, column, 0])) and torch.equal(
            rgb[rows, 1], torch.from_numpy(image[row, column, 1]))
        # distances along the ray: within [NEAR, FAR] x the view's distance to where the axes meet
        distance = (xyz[rows] - c2w[:, 3]).norm(dim=-1)
        to_target = float((TARGET - c2w[:, 3]) @ -c2w[:, 2])
        assert distance.min() >= NEAR * to_target - 1e-4 and distance.max() <= FAR * to_target + 1e-4
        # uniform in 1 / distance: half the points nearer than the harmonic middle
        middle = 2 / (1 / NEAR + 1 / FAR) * to_target
        assert (distance < middle).float().mean() == pytest.approx(0.5, abs=0.08)


@pytest.fixture(scope="module")
def run(tiny_scene, tmp_path_factory):
    cfg = short_config(tiny_scene, tmp_path_factory.mktemp("view-points"), steps=60, select_at=(20, 40), rounds=2,
                       initial=3, views_per_round=3, selector="random")
    cfg.pipeline.datamanager.seed_points = "random"
    cfg.pipeline.datamanager.random_points = "views"
    cfg.pipeline.datamanager.random_points_count = 800
    torch.manual_seed(0)
    return run_training(cfg)


def test_a_run_starts_from_points_in_front_of_its_views_and_redraws_them_at_its_restart(run):
    model, dm = run.pipeline.model, run.pipeline.datamanager
    assert model.random_start and model.view_points_start  # restarts at 6 views (twice the initial 3)
    log = json.loads((Path(run.base_dir) / "selected_views.json").read_text())
    first, second = log["rounds"]
    assert first["reset"] and first["after_add"]["view_points_restart"] == 800  # 3 -> 6 views: a restart
    assert not second.get("reset") and "view_points_restart" not in second.get("after_add", {})
    # the step-0 Gaussians later resets return to are the restart's points: drawn from all 6 views then active
    # (800 / 6 each, in view order), each block on its own view's rays
    means = model.initial_gaussians["means"]
    assert means.shape[0] == 800
    views = sorted(dm.initial_views + list(dm.history[0].chosen_indices))
    cams = dm.photo_cameras
    blocks = np.diff(np.linspace(0, 800, len(views) + 1).round().astype(int)).cumsum()
    for view, stop, start in zip(views, blocks, [0, *blocks[:-1]]):
        pose = cams.camera_to_worlds[view]
        local = (means[start:stop] - pose[:, 3]) @ pose[:, :3]
        depth = -local[:, 2]
        u = cams.fx[view] * local[:, 0] / depth + cams.cx[view]
        v = -cams.fy[view] * local[:, 1] / depth + cams.cy[view]
        assert (depth > 0).all() and (u >= 0).all() and (u <= cams.width[view]).all()
        assert (v >= 0).all() and (v <= cams.height[view]).all()
    assert math.isfinite(float(model.means.sum()))


def test_random_init_and_random_points_views_together_are_one_line(tiny_scene, tmp_path):
    from hpgs_ns.errors import OptionError

    cfg = short_config(tiny_scene, tmp_path, steps=10)
    cfg.pipeline.datamanager.random_points, cfg.pipeline.model.random_init = "views", True
    with pytest.raises(OptionError, match="random-init True starts from splatfacto's cube, so .*random-points views would do nothing"):
        run_training(cfg)


def test_a_bad_count_is_one_line(tiny_scene, tmp_path):
    from hpgs_ns.datamanager import ActiveViewError

    cfg = short_config(tiny_scene, tmp_path, steps=10)
    cfg.pipeline.datamanager.seed_points, cfg.pipeline.datamanager.random_points = "random", "views"
    cfg.pipeline.datamanager.random_points_count = 0
    with pytest.raises(ActiveViewError, match="random-points-count 0: must be at least 1"):
        run_training(cfg)
