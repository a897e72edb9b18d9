"""hpgs_ns.scenes.synthetic: the scene loads in nerfstudio's stock COLMAP parser with exact geometry, colours and
tracks; visibility and hidden objects are right; generation is deterministic, atomic and rejects bad arguments."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from hpgs_ns.errors import UserError
from hpgs_ns.scenes import synthetic as ss

SMALL = dict(num_cameras=16, width=96, height=72, num_points=600)


@pytest.fixture(scope="module")
def ring_scene(tmp_path_factory) -> Path:
    return ss.make_scene(tmp_path_factory.mktemp("ring") / "scene", layout="ring", seed=3, **SMALL)


@pytest.fixture(scope="module")
def occluded_scene(tmp_path_factory) -> Path:
    return ss.make_scene(
        tmp_path_factory.mktemp("occ") / "scene", layout="occluded", seed=0, num_cameras=36, width=48, height=36, num_points=2500
    )


@pytest.fixture(scope="module")
def parsed(ring_scene):
    """Stock nerfstudio COLMAP parser outputs for (train, test), with every point's 2D observations."""
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

    config = ColmapDataParserConfig(
        data=ring_scene,
        colmap_path=Path("sparse/0"),
        eval_mode="interval",
        eval_interval=8,
        downscale_factor=1,
        load_3D_points=True,
        max_2D_matches_per_3D_point=-1,
    )
    parser = config.setup()
    return parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")


def _truth(scene: Path) -> dict:
    return json.loads((scene / "ground_truth.json").read_text())


def _all_cameras(parsed):
    """Undo the interval split: image index (file-name order) -> (c2w (3, 4) OpenGL, fx, fy, cx, cy)."""
    train, test = parsed
    n = len(train.image_filenames) + len(test.image_filenames)
    test_idx = [i for i in range(n) if i % 8 == 0]
    train_idx = [i for i in range(n) if i % 8 != 0]
    cams = {}
    for outputs, idxs in ((train, train_idx), (test, test_idx)):
        c = outputs.cameras
        for k, i in enumerate(idxs):
            cams[i] = (c.camera_to_worlds[k].double().numpy(), float(c.fx[k]), float(c.fy[k]), float(c.cx[k]), float(c.cy[k]))
    return cams


def _project(cam, xyz: np.ndarray) -> np.ndarray:
    """Nerfstudio (OpenGL) camera, points (M, 3) in its world -> pixels (M, 2)."""
    c2w, fx, fy, cx, cy = cam
    p = (xyz - c2w[:, 3]) @ c2w[:, :3]  # camera frame: x right, y up, z back
    return np.stack([fx * p[:, 0] / -p[:, 2] + cx, fy * -p[:, 1] / -p[:, 2] + cy], 1)


def _observations(parsed):
    """-> points (P, 3), colours (P, 3), list of (point index, image index, keypoint xy) for every observation."""
    meta = parsed[0].metadata
    xyz = meta["points3D_xyz"].double().numpy()
    ids = meta["points3D_image_ids"].numpy()
    xy = meta["points3D_points2D_xy"].double().numpy()
    p, k = np.nonzero(ids >= 0)
    return xyz, meta["points3D_rgb"].numpy(), p, ids[p, k] - 1, xy[p, k]  # image ids are 1..N in file order


# ---------------------------------------------------------------------------------------------------------
# nerfstudio loads it


def test_stock_parser_loads_images_in_file_name_order_with_interval_split(ring_scene, parsed):
    train, test = parsed
    names = sorted(p.name for p in (ring_scene / "images").glob("*.png"))
    assert names == [f"{i:04d}.png" for i in range(16)]
    assert [p.name for p in test.image_filenames] == ["0000.png", "0008.png"]
    assert [p.name for p in train.image_filenames] == [n for i, n in enumerate(names) if i % 8 != 0]
    with Image.open(ring_scene / "images" / "0000.png") as im:
        assert im.size == (96, 72) and im.mode == "RGB"


def test_intrinsics_match_spec_and_ground_truth(ring_scene, parsed):
    truth = _truth(ring_scene)["intrinsics"]
    focal = 0.5 * 96 / math.tan(math.radians(60.0) / 2)
    cams = parsed[0].cameras
    assert truth == {"model": "PINHOLE", "width": 96, "height": 72, "fx": pytest.approx(focal), "fy": pytest.approx(focal),
                     "cx": 48.0, "cy": 36.0}
    assert cams.fx.unique().tolist() == pytest.approx([focal]) and cams.fy.unique().tolist() == pytest.approx([focal])
    assert cams.cx.unique().tolist() == [48.0] and cams.cy.unique().tolist() == [36.0]
    assert cams.width.unique().tolist() == [96] and cams.height.unique().tolist() == [72]
    assert float(cams.distortion_params.abs().max()) == 0.0


def test_poses_reproject_points_to_their_keypoints(parsed):
    cams = _all_cameras(parsed)
    xyz, _, p, img, xy = _observations(parsed)
    assert len(set(p.tolist())) == 600  # every point has observations
    err = np.zeros(len(p))
    for i in np.unique(img):
        m = img == i
        err[m] = np.linalg.norm(_project(cams[int(i)], xyz[p[m]]) - xy[m], axis=1)
    assert err.max() < 0.5
    assert np.median(err) < 0.01  # exact up to float32 round-off in nerfstudio's tensors


def test_keypoints_lie_in_the_image_and_tracks_have_two_views(parsed):
    meta = parsed[0].metadata
    ids = meta["points3D_image_ids"].numpy()
    counts = (ids >= 0).sum(1)
    assert counts.min() >= 2
    assert (meta["points3D_num_points2D"].numpy() == counts).all()
    for row in ids:  # an image appears at most once in a track
        seen = row[row >= 0]
        assert len(set(seen.tolist())) == len(seen)
    _, _, _, img, xy = _observations(parsed)
    assert set(img.tolist()) <= set(range(16))
    assert (xy >= 0).all() and (xy[:, 0] < 96).all() and (xy[:, 1] < 72).all()


def test_point_colours_equal_the_pixels_they_project_to(ring_scene, parsed):
    """Each observation's pixel shows the point's colour, and in-frame projections the track leaves out (the
    point is hidden there) show something else. Exact equality is not expected: a pixel is the 2x2 average of
    a texture that changes within it, so the centre value differs by a few levels (more at texture edges)."""
    images = {i: np.asarray(Image.open(ring_scene / "images" / f"{i:04d}.png"), dtype=np.int16) for i in range(16)}
    cams = _all_cameras(parsed)
    xyz, rgb, p, img, xy = _observations(parsed)
    rgb = rgb.astype(np.int16)

    def mismatch(points, image_ids, pixels):
        """max-channel |pixel - point colour| at the pixel, and the best over its 3x3 neighbourhood."""
        at, best = [], []
        for k, i, (x, y) in zip(points, image_ids, pixels):
            im = images[int(i)]
            at.append(np.abs(im[int(y), int(x)] - rgb[k]).max())
            patch = im[max(int(y) - 1, 0) : int(y) + 2, max(int(x) - 1, 0) : int(x) + 2].reshape(-1, 3)
            best.append(np.abs(patch - rgb[k]).max(1).min())
        return np.array(at), np.array(best)

    at, best = mismatch(p, img, xy)
    assert np.median(at) <= 4
    assert (best <= 10).mean() > 0.85

    tracked = set(zip(p.tolist(), img.tolist()))
    hidden_p, hidden_i, hidden_xy = [], [], []
    for i, cam in cams.items():
        uv = _project(cam, xyz)
        c2w = cam[0]
        in_front = ((xyz - c2w[:, 3]) @ c2w[:, 2]) < 0  # OpenGL cameras look along -z
        inside = in_front & (uv[:, 0] >= 0) & (uv[:, 0] < 96) & (uv[:, 1] >= 0) & (uv[:, 1] < 72)
        for k in np.flatnonzero(inside):
            if (int(k), i) not in tracked:
                hidden_p.append(k), hidden_i.append(i), hidden_xy.append(uv[k])
    assert len(hidden_p) > 0.2 * len(p)  # plenty of occluded projections (back sides, behind objects)
    h_at, h_best = mismatch(hidden_p, hidden_i, hidden_xy)
    assert np.median(h_at) > 5 * max(np.median(at), 1)
    assert (h_best <= 10).mean() < 0.6 * (best <= 10).mean()


# ---------------------------------------------------------------------------------------------------------
# visibility


def test_visibility_on_a_lone_sphere_is_the_facing_hemisphere():
    """Analytic check of the track rule: on a single convex sphere, a camera sees exactly the in-frame points
    whose normal faces it."""
    spec = ss.SceneSpec(num_cameras=8, num_rings=2, width=64, height=48)
    ball = ss.Sphere("ball", ss.Texture("solid", (1, 0, 0), (1, 0, 0)), center=(0.0, 0.0, 0.45), radius=0.6)
    scene = ss.Scene(prims=[ball], target=np.array([0.0, 0.0, 0.45]))
    cams = ss.camera_rig(spec, scene)
    rng = np.random.default_rng(0)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pts = np.array(ball.center) + 0.6 * n
    vis, uv = ss.visibility(scene, cams, pts, spec)
    for c, cam in enumerate(cams):
        facing = np.einsum("ij,ij->i", n, cam.center - pts) > 1e-3
        grazing = np.abs(np.einsum("ij,ij->i", n, cam.center - pts)) <= 1e-3
        assert (vis[c] == facing)[~grazing].all()
        assert (uv[c, vis[c]] >= 0).all() and (uv[c, vis[c], 0] < 64).all()


def test_visibility_respects_an_occluder():
    spec = ss.SceneSpec(num_cameras=4, num_rings=1, width=64, height=48)
    tex = ss.Texture("solid", (0.5, 0.5, 0.5), (0.5, 0.5, 0.5))
    ground = ss.Disc("ground", tex, role="ground", radius=9.0)
    scene = ss.Scene(prims=[ground], target=np.array([0.0, 0.0, 0.45]))
    cams = ss.camera_rig(spec, scene)
    # a tall wall between the origin and camera 0 only
    c0 = cams[0].center
    wall = ss.Box("wall", tex, role="occluder", center=(0.5 * c0[0], 0.5 * c0[1], 1.5), half=(0.1, 0.1, 1.5),
                  yaw_deg=math.degrees(math.atan2(c0[1], c0[0])))
    scene.prims.append(wall)
    point = np.array([[0.0, 0.0, 0.0]])  # on the ground at the centre
    vis, _ = ss.visibility(scene, cams, point, spec)
    assert vis[:, 0].tolist() == [False, True, True, True]


def test_occluded_layout_hides_the_pocket_object_from_most_cameras(occluded_scene):
    truth = _truth(occluded_scene)
    assert [h["name"] for h in truth["hidden"]] == ["gold_sphere"]
    seen_by = set(truth["hidden"][0]["seen_by"])
    cams = {c["name"]: c for c in truth["cameras"]}
    assert 2 <= len(seen_by) <= len(cams) / 3
    # only cameras facing the pocket's opening (+x side in the scene frame = azimuth near 0) see inside
    for name in seen_by:
        az = cams[name]["azimuth_deg"]
        assert min(az, 360 - az) < 70, (name, az)
    assert {c["name"] for c in truth["cameras"] if "gold_sphere" in c["sees"]} == seen_by
    assert truth["limited_visibility"][0]["name"] == "gold_sphere"
    # the pocket's interior is seen from every ring... and the other objects by most cameras
    for obj in truth["objects"]:
        if obj["name"] in ("red_sphere", "blue_cylinder", "ground", "backdrop"):
            assert len(obj["seen_by"]) > 0.6 * len(cams), obj["name"]


def test_hidden_object_points_are_tracked_only_by_cameras_that_see_it(occluded_scene):
    """Tracks (ray-cast points) agree with the layout and the rendered coverage: points on the gold sphere are
    observed only by cameras facing the pocket's opening, including most cameras whose images show it."""
    import pycolmap

    truth = _truth(occluded_scene)
    gold = next(o for o in truth["objects"] if o["name"] == "gold_sphere")
    rec = pycolmap.Reconstruction(str(occluded_scene / "sparse" / "0"))
    names = {image_id: image.name for image_id, image in rec.images.items()}
    observers = set()
    on_sphere = 0
    for point in rec.points3D.values():
        if abs(np.linalg.norm(point.xyz - np.array(gold["center"])) - gold["radius"]) < 1e-6:
            on_sphere += 1
            observers |= {names[e.image_id] for e in point.track.elements}
    assert on_sphere == gold["num_points3D"] == truth["hidden"][0]["num_points3D"] >= 5
    # only cameras facing the opening observe it (a point may sit on a sliver smaller than the 2 pixels that
    # `sees` asks for, so observers need not be a subset of seen_by)
    azimuth = {c["name"]: c["azimuth_deg"] for c in truth["cameras"]}
    assert all(min(azimuth[n], 360 - azimuth[n]) < 70 for n in observers), sorted(observers)
    assert len(observers) < len(truth["cameras"]) / 3
    assert len(observers & set(gold["seen_by"])) >= len(gold["seen_by"]) // 2


def test_ring_layout_wall_hides_the_magenta_sphere_from_the_far_side(ring_scene):
    truth = _truth(ring_scene)
    magenta = next(o for o in truth["objects"] if o["name"] == "magenta_sphere")
    assert truth["hidden"] == [{"name": "magenta_sphere", "seen_by": magenta["seen_by"], "num_points3D": magenta["num_points3D"]}]
    for cam in truth["cameras"]:
        az = cam["azimuth_deg"]
        if min(az, 360 - az) < 40:  # cameras on the +x side look at the wall's other face
            assert "magenta_sphere" not in cam["sees"], cam["name"]
    assert 0 < len(magenta["seen_by"]) < 16


def test_ground_truth_cameras_match_the_colmap_model(ring_scene):
    import pycolmap

    truth = _truth(ring_scene)
    rec = pycolmap.Reconstruction(str(ring_scene / "sparse" / "0"))
    assert truth["layout"] == "ring" and truth["seed"] == 3 and truth["num_points3D"] == rec.num_points3D() == 600
    assert sum(o["num_points3D"] for o in truth["objects"]) == 600
    assert sum(o["num_points3D"] for o in truth["objects"] if o["role"] in ("object", "occluder")) == 300  # default share 0.5
    assert all(o["num_points3D"] > 0 for o in truth["objects"])
    assert [c["name"] for c in truth["cameras"]] == [rec.images[i].name for i in sorted(rec.images)]
    assert [c["ring"] for c in truth["cameras"]] == [0] * 6 + [1] * 5 + [2] * 5
    up = np.array(truth["up"])
    heights = [float(np.dot(c["center"], up)) for c in truth["cameras"]]
    assert heights == pytest.approx([c["height"] for c in truth["cameras"]], abs=1e-5)
    for cam in truth["cameras"]:
        image = rec.images[cam["image_id"]]
        assert np.allclose(image.projection_center(), cam["center"], atol=1e-5)
        assert np.allclose(image.viewing_direction(), cam["look"], atol=1e-5)
        # cameras look at the target
        to_target = np.array(truth["target"]) - np.array(cam["center"])
        assert np.dot(to_target / np.linalg.norm(to_target), cam["look"]) > 0.9999
        assert set(cam["sees"]) >= {"ground"}
        assert all(cam["coverage"][n] >= 2 / (96 * 72) for n in cam["sees"])
    assert rec.compute_mean_reprojection_error() < 1e-6


# ---------------------------------------------------------------------------------------------------------
# determinism, atomic writes, errors


def _digest(scene: Path) -> dict:
    return {str(p.relative_to(scene)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(scene.rglob("*")) if p.is_file()}


def test_same_seed_gives_identical_files_and_another_seed_differs(tmp_path):
    kw = dict(layout="sparse-objects", num_cameras=6, width=32, height=24, num_points=100)
    a = _digest(ss.make_scene(tmp_path / "a", seed=5, **kw))
    b = _digest(ss.make_scene(tmp_path / "b", seed=5, **kw))
    c = _digest(ss.make_scene(tmp_path / "c", seed=6, **kw))
    assert a == b
    assert "sparse/0/points3D.bin" in a and "images/0005.png" in a and "ground_truth.json" in a
    assert a["images/0000.png"] != c["images/0000.png"] and a["sparse/0/points3D.bin"] != c["sparse/0/points3D.bin"]


def test_a_failed_run_leaves_nothing_behind(tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise KeyboardInterrupt  # as if the run were killed while writing the model

    monkeypatch.setattr(ss, "_write_colmap", boom)
    with pytest.raises(KeyboardInterrupt):
        ss.make_scene(tmp_path / "scene", num_cameras=4, width=16, height=12, num_points=10)
    assert list(tmp_path.iterdir()) == []


def test_existing_output_needs_overwrite_and_is_replaced_whole(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    kw = dict(num_cameras=4, width=16, height=12, num_points=10)
    with pytest.raises(ss.SceneSpecError, match="not empty; pass --overwrite"):
        ss.make_scene(out, **kw)
    assert (out / "stale.txt").exists()
    ss.make_scene(out, overwrite=True, **kw)
    assert not (out / "stale.txt").exists() and (out / "sparse" / "0" / "images.bin").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]  # no temp or old folders left
    ss.make_scene(tmp_path / "empty-ok", **kw)  # a new folder needs no flag
    (tmp_path / "empty").mkdir()
    ss.make_scene(tmp_path / "empty", **kw)  # nor does an existing empty one


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(layout="spiral"), "unknown layout 'spiral'"),
        (dict(num_cameras=1), "--num-cameras must be >= 2"),
        (dict(num_cameras=3, num_rings=4), "--num-cameras must be >= 2 and >= --num-rings"),
        (dict(num_rings=0), "--num-rings must be >= 1"),
        (dict(width=4), "at least 8x8"),
        (dict(num_points=-1), "--num-points must be >= 0"),
        (dict(fov_deg=179.0), "--fov-deg"),
        (dict(supersample=0), "--supersample"),
        (dict(object_point_fraction=1.5), "--object-point-fraction"),
    ],
)
def test_bad_arguments_raise_one_line_errors(tmp_path, kwargs, message):
    with pytest.raises(ss.SceneSpecError, match=message) as err:
        ss.make_scene(tmp_path / "scene", **kwargs)
    assert "\n" not in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_output_path_that_is_a_file_is_rejected(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(ss.SceneSpecError, match="not a folder"):
        ss.make_scene(tmp_path / "f")


def test_cli_writes_the_scene_and_reports_bad_arguments(tmp_path, capsys):
    import tyro

    cmd = tyro.cli(ss.MakeScene, args=["--out", str(tmp_path / "s"), "--layout", "occluded", "--num-cameras", "5",
                                       "--width", "24", "--height", "18", "--num-points", "50", "--seed", "2"])
    cmd.main()
    out = capsys.readouterr().out
    assert out.startswith(f"wrote {tmp_path / 's'}: 5 images 24x18") and "layout occluded, seed 2" in out
    assert _truth(tmp_path / "s")["spec"]["num_cameras"] == 5
    refused = r"^hpgs make-scene: output folder .* exists and is not empty; pass --overwrite"
    with pytest.raises(UserError, match=refused) as info:
        cmd.main()  # now exists and is not empty
    assert "\n" not in str(info.value) and capsys.readouterr().err == ""
    with pytest.raises(SystemExit):
        tyro.cli(ss.MakeScene, args=["--layout", "spiral"])
    assert (ss.MakeScene.__doc__ or "").strip().splitlines()[0].startswith("Generate")
