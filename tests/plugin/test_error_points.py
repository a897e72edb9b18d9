"""`--pipeline.selection.after-add.error-points`: Gaussians seeded on the rays of the pixels a new view's render
gets wrong (`hpgs_ns.scenes.error_points`), and the round that adds them on the tiny scene."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import short_config
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hpgs_ns.render.viewmats import world_to_camera
from hpgs_ns.scenes.error_points import OPAQUE, error_weights, pixel_errors, points_where_render_errs
from hpgs_ns.scenes.view_points import FAR, NEAR
from hpgs_ns.selection.after_add import AfterAddConfig, AfterAddError

H, W = 12, 16
K = torch.tensor([[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]])
DEPTH, DISTANCE = 2.5, 4.0
PATCH = (slice(3, 6), slice(5, 9))  # 3 x 4 pixels the render gets wrong


def camera_to_world() -> torch.Tensor:
    """An OpenGL pose turned 30 degrees about y, away from the origin."""
    a = math.radians(30)
    rotation = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    return torch.cat([rotation, torch.tensor([[1.0], [-0.5], [3.0]])], dim=1)


def scene():
    """A photo with a distinct colour per pixel, a render equal to it but white on PATCH, opaque on PATCH's left half."""
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    photo = torch.stack([ys / (H - 1), xs / (W - 1), torch.full((H, W), 0.2)], dim=-1)
    render = photo.clone()
    render[PATCH] = 1.0
    depth = torch.full((H, W, 1), DEPTH)
    alpha = torch.zeros(H, W, 1)
    alpha[3:6, 5:7] = 1.0
    return render, depth, alpha, photo


def project(xyz: torch.Tensor):
    """World points -> (pixel x, pixel y, z) in the test camera (OpenCV camera space, as the rasterizer)."""
    view = world_to_camera(camera_to_world()[None])[0]
    cam = xyz @ view[:3, :3].T + view[:3, 3]
    return cam[:, 0] / cam[:, 2] * K[0, 0] + K[0, 2], cam[:, 1] / cam[:, 2] * K[1, 1] + K[1, 2], cam[:, 2]


def test_points_lie_on_the_wrong_pixels_rays_in_the_photos_colours():
    render, depth, alpha, photo = scene()
    xyz, rgb = points_where_render_errs(K, camera_to_world(), render, depth, alpha, photo, 100, DISTANCE,
                                        torch.Generator().manual_seed(0))
    assert xyz.shape == (12, 3) and rgb.dtype == torch.uint8  # every wrong pixel once, no other pixel
    u, v, z = project(xyz)
    x, y = (u - 0.5).round().long(), (v - 0.5).round().long()
    assert torch.allclose(u, x + 0.5, atol=1e-3) and torch.allclose(v, y + 0.5, atol=1e-3)  # pixel centres
    assert set(zip(y.tolist(), x.tolist())) == {(r, c) for r in range(3, 6) for c in range(5, 9)}
    opaque = alpha[y, x, 0] >= OPAQUE
    assert int(opaque.sum()) == 6
    assert torch.allclose(z[opaque], torch.full((6,), DEPTH), atol=1e-4)  # the render's depth where it is opaque
    drawn = z[~opaque]
    assert bool(((drawn >= NEAR * DISTANCE - 1e-4) & (drawn <= FAR * DISTANCE + 1e-4)).all())
    assert len(set(drawn.round(decimals=4).tolist())) == 6  # drawn, not one fixed depth
    assert torch.equal(rgb, (photo[y, x] * 255).round().to(torch.uint8))


@settings(max_examples=40, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(quat=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: sum(v * v for v in q) > 0.01),
       centre=st.lists(st.floats(-3, 3), min_size=3, max_size=3), focal=st.floats(5, 5000),
       depth=st.floats(0.05, 50), distance=st.floats(0.05, 50))
def test_any_pose_puts_each_point_on_its_pixels_ray(quat, centre, focal, depth, distance):
    # nerfstudio's normalised frame: cameras within [-1, 1] (a little beyond), scene depths of 0.05-50
    w, x, y, z = torch.nn.functional.normalize(torch.tensor(quat, dtype=torch.float64), dim=0).tolist()
    rotation = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                             [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                             [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    pose = torch.cat([rotation, torch.tensor(centre, dtype=torch.float64)[:, None]], dim=1).float()
    k = torch.tensor([[focal, 0.0, W / 2], [0.0, focal, H / 2], [0.0, 0.0, 1.0]])
    render, _, alpha, photo = scene()
    xyz, rgb = points_where_render_errs(k, pose, render, torch.full((H, W, 1), depth), alpha, photo, 12, distance,
                                        torch.Generator().manual_seed(1))
    assert xyz.shape == (12, 3) and bool(torch.isfinite(xyz).all())
    view = world_to_camera(pose.double()[None])[0]
    cam = xyz.double() @ view[:3, :3].T + view[:3, 3]
    u, v = cam[:, 0] / cam[:, 2] * focal + W / 2, cam[:, 1] / cam[:, 2] * focal + H / 2
    assert torch.allclose(u, (u - 0.5).round() + 0.5, atol=0.05) and torch.allclose(v, (v - 0.5).round() + 0.5, atol=0.05)
    pixels = {(int(r), int(c)) for r, c in zip((v - 0.5).round().tolist(), (u - 0.5).round().tolist())}
    assert pixels == {(r, c) for r in range(3, 6) for c in range(5, 9)}  # the wrong pixels, each once
    opaque = torch.tensor([c < 7 for _, c in sorted(pixels)])  # PATCH's left half
    by_pixel = dict(zip(zip((v - 0.5).round().long().tolist(), (u - 0.5).round().long().tolist()), cam[:, 2].tolist()))
    z = torch.tensor([by_pixel[p] for p in sorted(pixels)])
    assert torch.allclose(z[opaque], torch.full((6,), depth, dtype=z.dtype), rtol=1e-5)
    assert bool(((z[~opaque] >= NEAR * distance * (1 - 1e-5)) & (z[~opaque] <= FAR * distance * (1 + 1e-5))).all())


def test_the_draws_favour_larger_errors_and_stop_at_count():
    render, depth, alpha, photo = scene()
    render[3:6, 5:7] = photo[3:6, 5:7] + 0.05  # half the patch a little wrong, half very wrong
    counts = torch.zeros(2)
    for seed in range(200):
        xyz, _ = points_where_render_errs(K, camera_to_world(), render, depth, alpha, photo, 3, DISTANCE,
                                          torch.Generator().manual_seed(seed))
        assert xyz.shape == (3, 3)
        x = (project(xyz)[0] - 0.5).round().long()
        counts += torch.stack([(x < 7).sum(), (x >= 7).sum()]).float()
    # weights 0.05 and ~0.6-0.8 per pixel: without replacement, the small-error pixels get far fewer draws
    assert counts[0] < 0.15 * counts.sum() and counts[1] > 0.85 * counts.sum()


def test_no_error_no_points_and_the_median_cut():
    render, depth, alpha, photo = scene()
    xyz, rgb = points_where_render_errs(K, camera_to_world(), photo, depth, alpha, photo, 50, DISTANCE)
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
    errors = torch.tensor([[0.1, 0.2], [0.3, 0.4]])
    assert torch.equal(error_weights(errors), torch.tensor([[0.0, 0.0], [0.3, 0.4]]))  # median 0.2: at or below it, 0
    plain = torch.tensor([[0.5, 0.5], [0.5, 0.2]])  # nothing above the median (0.5): every pixel's error
    assert torch.equal(error_weights(plain), plain)
    assert torch.allclose(pixel_errors(torch.ones(1, 1, 3), torch.tensor([[[0.0, 0.5, 1.0]]])), torch.tensor([[0.5]]))
    with pytest.raises(ValueError, match=r"\(12, 16\) render of a \(6, 8\) photo"):
        points_where_render_errs(K, camera_to_world(), render, depth, alpha, photo[:6, :8], 5, DISTANCE)


def test_a_negative_count_is_one_line():
    with pytest.raises(AfterAddError, match="error-points -1 must be a whole number of points per view >= 0"):
        AfterAddConfig(error_points=-1)
    assert AfterAddConfig(error_points=2000).describe() == "error-points 2000"


def test_a_round_adds_gaussians_where_its_view_renders_wrong(tiny_scene, tmp_path, capsys):
    cfg = short_config(tiny_scene, tmp_path, steps=4, select_at=(2,), rounds=1, selector="farthest")
    cfg.pipeline.selection.after_add = AfterAddConfig(error_points=300)
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    model, dm = trainer.pipeline.model, trainer.pipeline.datamanager
    before = model.num_points
    trainer.train()
    record = dm.history[0]
    added = int(record.after_add["error_points_added"])
    assert added == 300  # a splat two steps old renders most of a 64 x 48 view wrong
    assert model.num_points == before + added  # refinement is off at these steps: only the round grew the splat
    new = model.means[before:].detach().cpu()
    view = record.chosen_indices[0]
    camera = dm.train_cameras[view : view + 1]
    cam = new @ world_to_camera(camera.camera_to_worlds)[0, :3, :3].T + world_to_camera(camera.camera_to_worlds)[0, :3, 3]
    assert bool((cam[:, 2] > 0).all())  # in front of the new view ...
    k = camera.get_intrinsics_matrices()[0]
    u, v = cam[:, 0] / cam[:, 2] * k[0, 0] + k[0, 2], cam[:, 1] / cam[:, 2] * k[1, 1] + k[1, 2]
    assert bool(((u >= 0) & (u <= 64) & (v >= 0) & (v <= 48)).all())  # ... and inside its frame
    out = capsys.readouterr().out
    assert "error points after round 1: 300 Gaussians where the render of its 1 new view(s) was wrong" in out


def test_reset_after_add_says_error_points_does_nothing(tiny_scene, tmp_path, capsys):
    cfg = short_config(tiny_scene, tmp_path, steps=4, select_at=(2,), rounds=1, selector="farthest",
                       reset_after_add=True)
    cfg.pipeline.selection.after_add = AfterAddConfig(error_points=300)
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    assert "error_points_added" not in trainer.pipeline.datamanager.history[0].after_add
    assert "error-points does nothing in this run: reset-after-add" in capsys.readouterr().out


def test_a_run_without_rounds_says_error_points_does_nothing(tiny_scene, tmp_path, capsys):
    cfg = short_config(tiny_scene, tmp_path, steps=2, rounds=0)
    cfg.pipeline.selection.after_add = AfterAddConfig(error_points=300)
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    before = trainer.pipeline.model.num_points
    trainer.train()
    assert "error-points does nothing in this run: no round adds views" in capsys.readouterr().out
    assert trainer.pipeline.model.num_points == before  # nothing added (refinement is off at these steps)
