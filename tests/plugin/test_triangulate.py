"""Seed points triangulated from the active views alone, at their known poses (hpgs_ns.scenes.triangulate):
nerfstudio's camera conventions carried into COLMAP exactly, points where juicebox's own COLMAP model has them
(both in nerfstudio's normalised frame), a nerfstudio-data capture with no COLMAP model, a later call reusing
the earlier views' features, and one line instead of a traceback when nothing can be triangulated."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import require_shared
from helpers import look_at_cameras, two_views_of_points
from PIL import Image

from hpgs_ns.scenes.triangulate import (
    COLMAP_DEFAULTS,
    DEFAULT_SETTINGS,
    TriangulationWorkspace,
    colmap_cam_from_world,
    colmap_camera_model,
    epipolar_distance,
    seed_points,
    triangulate_views,
    view_pairs,
)

JUICEBOX_VIEWS = 8


@pytest.mark.parametrize("kind,distortion", [
    ("PERSPECTIVE", [0.0] * 6),
    ("PERSPECTIVE", [0.05, -0.02, 0.0, 0.0, 0.001, -0.002]),  # OPENCV
    ("PERSPECTIVE", [0.05, -0.02, 0.01, 0.0, 0.001, -0.002]),  # FULL_OPENCV (k3)
    ("FISHEYE", [0.03, -0.01, 0.002, 0.0, 0.0, 0.0]),
])
def test_a_point_on_a_nerfstudio_ray_projects_back_to_its_pixel_in_colmap(kind, distortion):
    import pycolmap
    from nerfstudio.cameras.cameras import CameraType

    cameras = look_at_cameras(3, camera_type=getattr(CameraType, kind), distortion_params=torch.tensor([distortion] * 3))
    pixels = torch.tensor([[10.5, 20.5], [120.0, 160.0], [230.25, 300.75]])  # (y, x), as nerfstudio's coords
    for i in range(len(cameras)):
        model, width, height, params = colmap_camera_model(cameras, i)
        camera = pycolmap.Camera(model=model, width=width, height=height, params=params)
        rays = cameras.generate_rays(camera_indices=i, coords=pixels)
        points = (rays.origins + 2.5 * rays.directions).double().numpy()
        cam_from_world = pycolmap.Rigid3d(colmap_cam_from_world(cameras.camera_to_worlds[i]))
        in_camera = np.stack([cam_from_world * p for p in points])
        assert (in_camera[:, 2] > 0).all()  # COLMAP's z looks forward
        projected = np.stack([camera.img_from_cam(p) for p in in_camera])
        assert np.abs(projected - pixels.flip(-1).numpy()).max() < 0.05, (model, projected)


def test_known_pose_verification_keeps_true_matches_and_drops_a_planted_wrong_one():
    """The epipolar distance under the known relative pose (lens distortion removed): ~0 px for the projections of
    one 3D point, large for a match that pairs two different points."""
    colmap_cameras, cam2_from_cam1, pixels = two_views_of_points()
    wrong = np.argmax(np.abs(pixels[1][:, 1] - pixels[1][0, 1]))  # point 0's pixel in view a with a far-off point's in b
    points1 = np.concatenate([pixels[0], pixels[0][:1]])
    points2 = np.concatenate([pixels[1], pixels[1][wrong:wrong + 1]])
    distance = epipolar_distance(*colmap_cameras, cam2_from_cam1, points1, points2)
    assert distance[:-1].max() < 0.01 and distance[-1] > 20, distance[-1]  # pixels


def test_the_package_runs_only_the_verifications_users_run():
    """Guided matching, a rejected variant, lives in benchmarks/triangulation_variants.py
    (tests/lab/test_triangulation_variants.py); the package's settings refuse it."""
    from hpgs_ns.scenes.triangulate import TriangulationSettings

    with pytest.raises(ValueError, match="'ransac' or 'poses'"):
        TriangulationSettings(verification="guided")


def test_unsupported_camera_types_fail_in_one_line(tmp_path):
    from nerfstudio.cameras.cameras import CameraType

    cameras = look_at_cameras(2, camera_type=CameraType.EQUIRECTANGULAR)
    paths = flat_images(tmp_path, 2)
    xyz, rgb, info = triangulate_views(cameras, paths, [0, 1])
    assert info.failed and not info.ok and xyz.shape == (0, 3) and rgb.shape == (0, 3)
    assert "EQUIRECTANGULAR" in info.message and "\n" not in info.message


def test_beyond_max_exhaustive_each_view_is_matched_with_its_nearest_views():
    cameras = look_at_cameras(12)
    views = list(range(0, 12))
    assert len(view_pairs(cameras, views, max_exhaustive=12, neighbours=2)) == 66  # every pair
    pairs = view_pairs(cameras, views, max_exhaustive=8, neighbours=2)
    assert all(a < b for a, b in pairs) and len(set(pairs)) == len(pairs)
    # on a ring, a view's 2 nearest are its neighbours either side; opposite views (facing each other) never pair
    assert set(pairs) == {(k, (k + 1) % 12) if k < 11 else (0, 11) for k in range(12)}


def test_photos_are_downscaled_and_blender_rgba_is_put_on_white(tmp_path):
    from hpgs_ns.scenes.triangulate import TriangulationError, _write_view_image

    pixels = np.zeros((300, 400, 4), np.uint8)
    pixels[:, :200] = (200, 10, 10, 255)  # left half opaque red, right half transparent
    Image.fromarray(pixels, "RGBA").save(tmp_path / "r_0.png")
    size = _write_view_image(tmp_path / "r_0.png", tmp_path / "out.png", 200, (800, 600))
    with Image.open(tmp_path / "out.png") as out:
        assert size == out.size == (200, 150) and out.mode == "RGB"
        assert out.getpixel((20, 75)) == (200, 10, 10) and out.getpixel((180, 75)) == (255, 255, 255)
    with pytest.raises(TriangulationError, match="r_0.png is 400x300 but its camera says 400x400"):
        _write_view_image(tmp_path / "r_0.png", tmp_path / "out.png", 200, (400, 400))


def flat_images(folder: Path, num: int, noise_every: int = 0) -> list:
    """`num` 160x120 photos of one flat colour, or (every `noise_every`-th) of uniform noise: nothing matches."""
    rng = np.random.default_rng(0)
    paths = []
    for k in range(num):
        noisy = noise_every and k % noise_every == 0
        pixels = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) if noisy else np.full((120, 160, 3), (90, 120, 200), np.uint8)
        paths.append(folder / f"{k}.png")
        Image.fromarray(pixels).save(paths[-1])
    return paths


def test_views_without_usable_matches_fall_back_with_one_line(tmp_path, capsys):
    cameras, paths = look_at_cameras(6), flat_images(tmp_path, 6, noise_every=2)
    xyz, rgb, info = triangulate_views(cameras, paths, range(6))
    assert not info.ok and not info.failed and info.num_points == xyz.shape[0] < info.min_points
    assert seed_points(cameras, paths, range(6)) is None
    out = capsys.readouterr()
    lines = [line for line in (out.out + out.err).splitlines() if line.strip()]
    assert len(lines) == 1, lines  # COLMAP's own log is kept quiet too
    assert f"only {info.num_points} points triangulated from 6 views" in lines[0] and "random points" in lines[0]


def test_a_pycolmap_failure_is_one_line_and_the_workspace_starts_over(tmp_path, capfd):
    cameras, paths = look_at_cameras(3), flat_images(tmp_path, 3)
    with TriangulationWorkspace(parent=tmp_path) as workspace:
        workspace.database.write_bytes(b"not a database" * 64)
        xyz, rgb, info = triangulate_views(cameras, paths, [0, 1, 2], existing=workspace)
        assert info.failed and not info.ok and xyz.shape == (0, 3)
        assert info.message.startswith("triangulation of 3 views failed: RuntimeError: ") and "\n" not in info.message
        assert not any(workspace.root.iterdir())  # nothing half-written is kept
        _, _, again = triangulate_views(cameras, paths, [0, 1, 2], existing=workspace)
        assert not again.failed
    assert not workspace.root.exists()
    out = capfd.readouterr()
    assert not (out.out + out.err).strip()


# ---- real captures -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def juicebox():
    """juicebox's training views at half width and height (images_2, 400x224: a quarter of the pixels), parsed
    as `ns-train hpgs` does, with its COLMAP points (built from all 64 photos) in nerfstudio's normalised frame."""
    from hpgs_ns.dataparser import MipNerf360DataParserConfig

    data = require_shared("data", "juicebox")
    if not (data / "images_2").is_dir():  # the parser would write it into the shared folder
        pytest.skip(f"{data / 'images_2'} not found")
    outputs = MipNerf360DataParserConfig(data=data, downscale_factor=2).setup().get_dataparser_outputs("train")
    views = np.linspace(0, len(outputs.image_filenames) - 1, JUICEBOX_VIEWS).round().astype(int).tolist()
    return outputs, views


@pytest.fixture(scope="module")
def juicebox_points(juicebox):
    outputs, views = juicebox
    return triangulate_views(outputs.cameras, outputs.image_filenames, views)


def scene_extent(points: np.ndarray) -> float:
    """Diagonal of the box between the 5th and 95th percentiles on each axis (COLMAP's far outliers excluded)."""
    low, high = np.percentile(points, [5, 95], axis=0)
    return float(np.linalg.norm(high - low))


def test_juicebox_points_lie_on_its_colmap_model_with_its_colours(juicebox, juicebox_points):
    from scipy.spatial import cKDTree

    outputs, views = juicebox
    xyz, rgb, info = juicebox_points
    assert info.ok and not info.message and info.num_views == JUICEBOX_VIEWS
    assert xyz.dtype == torch.float32 and rgb.dtype == torch.uint8 and xyz.shape == rgb.shape and xyz.shape[0] >= 200
    reference = outputs.metadata["points3D_xyz"].numpy()
    distance, nearest = cKDTree(reference).query(xyz.numpy())
    assert np.median(distance) < 0.01 * scene_extent(reference)
    # stricter: as close to COLMAP's points as those are to one another
    spacing = cKDTree(reference).query(reference, k=2)[0][:, 1]
    assert np.median(distance) < np.median(spacing)
    colour_error = np.abs(rgb.numpy().astype(int) - outputs.metadata["points3D_rgb"].numpy()[nearest].astype(int))
    assert np.median(colour_error) < 20
    # in front of every view that triangulated them: nerfstudio cameras look down -z
    c2w = outputs.cameras.camera_to_worlds[views]
    depth = -((xyz[None] - c2w[:, None, :, 3]) * c2w[:, None, :, 2]).sum(-1)
    assert (depth.max(0).values > 0).all()


def test_a_later_round_extracts_and_matches_only_its_new_views(juicebox, juicebox_points):
    outputs, views = juicebox
    first, added = views[:6], views[6:]
    with TriangulationWorkspace() as workspace:
        _, _, before = triangulate_views(outputs.cameras, outputs.image_filenames, first, existing=workspace)
        xyz, _, after = triangulate_views(outputs.cameras, outputs.image_filenames, first + added, existing=workspace)
    assert before.ok and before.new_views == 6 and before.pairs_matched == 15
    assert after.ok and after.new_views == 2 and after.pairs_matched == 2 * 6 + 1
    assert after.num_points > before.num_points
    assert abs(after.num_points - juicebox_points[2].num_points) <= 0.05 * juicebox_points[2].num_points  # as one call over all 8


def test_known_pose_verification_yields_more_points_than_colmaps_ransac_as_accurate(juicebox, juicebox_points):
    """The default (matches checked against the known poses, ratio 0.9, 5 inliers a pair) against COLMAP's own
    two-view RANSAC one keyword away, on juicebox's 8 views: 409 against 316 points here (2 cores)."""
    from scipy.spatial import cKDTree

    outputs, views = juicebox
    assert DEFAULT_SETTINGS.verification == "poses" and COLMAP_DEFAULTS.verification == "ransac"
    xyz, _, info = juicebox_points
    old_xyz, _, old = triangulate_views(outputs.cameras, outputs.image_filenames, views, settings=COLMAP_DEFAULTS)
    assert old.ok and info.num_points >= 1.15 * old.num_points, (info.num_points, old.num_points)
    reference = outputs.metadata["points3D_xyz"].numpy()
    tree, extent = cKDTree(reference), scene_extent(reference)
    new_error, old_error = (float(np.median(tree.query(p.numpy())[0])) / extent for p in (xyz, old_xyz))
    assert new_error < 0.01 and new_error < 1.5 * old_error, (new_error, old_error)


def test_a_nerfstudio_data_capture_with_distortion_and_no_colmap_model():
    from hpgs_ns.dataparser import HpgsNerfstudioDataParserConfig

    data = require_shared("data", "fox-nerfstudio")
    if not (data / "images_4").is_dir():
        pytest.skip(f"{data / 'images_4'} not found")
    outputs = HpgsNerfstudioDataParserConfig(data=data, downscale_factor=4).setup().get_dataparser_outputs("train")
    assert outputs.cameras.distortion_params.abs().sum() > 0  # k1, k2, p1, p2 from transforms.json
    views = np.linspace(0, len(outputs.image_filenames) - 1, 8).round().astype(int).tolist()
    xyz, rgb, info = triangulate_views(outputs.cameras, outputs.image_filenames, views)
    assert info.ok and info.num_points >= 200 and info.mean_reprojection_error < 1.0
    c2w = outputs.cameras.camera_to_worlds[views]
    depth = -((xyz[None] - c2w[:, None, :, 3]) * c2w[:, None, :, 2]).sum(-1)
    assert (depth > 0).float().mean() > 0.95  # the fox sits in front of the ring of cameras
