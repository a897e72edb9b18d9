"""Seed points triangulated from the active views only, at their known poses: no test photo is ever used.

splatfacto's seed points usually come from the capture's COLMAP model, which was built from every photo,
test photos included (a leak), and which a capture in progress does not have at all (nerfstudio-data, Blender).
Here pycolmap extracts SIFT features (CPU) from the given views, matches them among themselves (every pair up
to `max_exhaustive` views, else each view with its nearest views by camera centre), keeps the matches that agree
with the KNOWN relative pose of the pair (within a few pixels of their epipolar lines; COLMAP's own two-view
RANSAC, which rejects wide-baseline pairs with few matches, is `settings=COLMAP_DEFAULTS`), and triangulates with
the poses held fixed, so the points are in the cameras' own frame: nerfstudio's normalised (auto-oriented,
scaled) frame, the frame of `cameras.camera_to_worlds`, in its units. Another matcher (pose-guided matching, say)
plugs in by overriding `TriangulationWorkspace.match_pairs`.

One call (a temporary folder, removed at the end):

    xyz, rgb, info = triangulate_views(dataset.cameras, dataset.image_filenames, active)
    if info.ok:  # else xyz is [0, 3] or fewer than min_points; info.message is one line saying why
        metadata["points3D_xyz"], metadata["points3D_rgb"] = xyz, rgb    # [N, 3] float32, [N, 3] uint8

or `seed_points(...)`, which prints that one line and returns None when the caller should fall back to random
points. After a round adds views, pass the same `TriangulationWorkspace` each time: features and matches of the
views seen before are kept, so only the new views are extracted and only pairs with a new view are matched.

    with TriangulationWorkspace() as ws:
        xyz, rgb, info = triangulate_views(cameras, paths, active, existing=ws)
        ...                                     # a round adds views to `active`
        xyz, rgb, info = triangulate_views(cameras, paths, active, existing=ws)

Nothing here raises for a scene without usable matches or a pycolmap failure: the result is flagged
(`info.ok` False, `info.failed` True for a failure) with a one-line `info.message`.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch
from PIL import Image

from hpgs_ns.errors import UserError

DEFAULT_MAX_IMAGE_SIZE = 640  # fox (540x960), 8 views, 2 cores: 640 px 1204 points in 10 s, 800 px 1559 in 19 s
DEFAULT_MIN_POINTS = 100
DEFAULT_MAX_EXHAUSTIVE = 30  # 30 views = 435 pairs; beyond, each view is matched with its nearest views only
DEFAULT_NEIGHBOURS = 12


@dataclass(frozen=True)
class TriangulationSettings:
    """How features are found, matched and verified. `COLMAP_DEFAULTS`: COLMAP's own (SIFT's defaults, two-view
    geometry by RANSAC on an essential/fundamental matrix, at least 15 inliers a pair).

    peak_threshold: SIFT's peak threshold (COLMAP's default 0.02 / 3; lower finds more, weaker features).
    max_num_features: SIFT features kept per image.
    max_ratio: the matcher's ratio test (second-nearest over nearest descriptor distance).
    verification: "ransac": COLMAP's two-view estimation decides each pair's inlier matches; "poses": the
        matches are checked against the KNOWN relative pose instead (no estimation): a match is kept when both
        its keypoints lie within `max_epipolar_error` pixels of the other's epipolar line.
    max_epipolar_error: pixels at the size SIFT saw ("poses").
    min_num_inliers: a pair needs at least this many inlier matches to be used (RANSAC's minimum and the
        triangulator's `min_num_matches`).
    """

    peak_threshold: float = 0.02 / 3
    max_num_features: int = 8192
    max_ratio: float = 0.8
    verification: str = "ransac"
    max_epipolar_error: float = 4.0
    min_num_inliers: int = 15

    def __post_init__(self) -> None:
        if self.verification not in ("ransac", "poses"):
            raise ValueError(f"verification {self.verification!r}: 'ransac' or 'poses'")


COLMAP_DEFAULTS = TriangulationSettings()
# Chosen on the tuning scenes: checking matches against the known poses, with a looser ratio test and 5 inliers a
# pair, yields nearly twice COLMAP_DEFAULTS' points from 4-8 views, as accurate, in the same time.
KNOWN_POSES = TriangulationSettings(max_ratio=0.9, verification="poses", min_num_inliers=5)
DEFAULT_SETTINGS = KNOWN_POSES


class TriangulationError(UserError):
    """Triangulation could not run (pycolmap failing, an unreadable image, a camera type COLMAP lacks).
    `triangulate_views` returns it as `info.message` instead of raising; `TriangulationInfo.raise_if_failed` raises."""


class PycolmapMissingError(UserError):
    """pycolmap cannot be imported. Raised, never returned as a message: falling back to random points for an
    install problem would give a random start's numbers under the active start's name."""


def require_pycolmap(what: str, other_fix: str = "") -> None:
    """Raise `PycolmapMissingError` (one line: `what` needs it, and the fix) unless pycolmap imports."""
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        raise PycolmapMissingError(f"{what} needs pycolmap, which is not installed here: pip install pycolmap"
                                   + (f" ({other_fix})" if other_fix else "")) from None


@dataclass
class TriangulationInfo:
    """What a call did. `ok`: at least `min_points` points and no failure. `message`: one line when not ok."""

    ok: bool
    num_points: int
    num_views: int
    min_points: int
    failed: bool = False
    message: str = ""
    new_views: int = 0  # views whose features were extracted by this call (the rest came from the workspace)
    pairs_matched: int = 0  # image pairs matched by this call
    mean_track_length: float = 0.0
    mean_reprojection_error: float = 0.0  # pixels, at the downscaled size
    seconds: Dict[str, float] = field(default_factory=dict)  # by stage, and "total"

    def raise_if_failed(self) -> None:
        if not self.ok:
            raise TriangulationError(self.message)


def triangulate_views(
    cameras,
    image_paths: Sequence[Path],
    indices: Sequence[int],
    *,
    max_image_size: int = DEFAULT_MAX_IMAGE_SIZE,
    min_points: int = DEFAULT_MIN_POINTS,
    max_exhaustive: int = DEFAULT_MAX_EXHAUSTIVE,
    neighbours: int = DEFAULT_NEIGHBOURS,
    two_view_tracks: bool = True,
    num_threads: int = -1,
    existing: Optional[TriangulationWorkspace] = None,
    settings: TriangulationSettings = DEFAULT_SETTINGS,
) -> Tuple[torch.Tensor, torch.Tensor, TriangulationInfo]:
    """Triangulate points from the views `indices` of `cameras` at their known poses.

    cameras: nerfstudio `Cameras` [M] (camera_to_worlds [M, 3, 4] OpenGL convention: x right, y up, z back;
        fx, fy, cx, cy, width, height; distortion_params [k1, k2, k3, k4, p1, p2]); PERSPECTIVE or FISHEYE.
    image_paths: [M] the photo of each camera (any size with the camera's aspect ratio; RGBA is put on white).
    indices: which views to use (e.g. the active training views); at least 2.
    max_image_size: photos are downscaled so their longer side is at most this (pixels) before SIFT.
    min_points: fewer points -> `info.ok` False (the points are still returned) and a one-line message.
    max_exhaustive: up to this many views every pair is matched; beyond, each view with its `neighbours`
        nearest views by camera centre.
    two_view_tracks: keep points seen by only two views (most of the points when there are few views).
    num_threads: pycolmap's threads for extraction and matching (-1: all cores).
    existing: a `TriangulationWorkspace` kept between calls (features and matches of earlier views are reused);
        None: a temporary one for this call.
    settings: features, matching and verification (`TriangulationSettings`); `COLMAP_DEFAULTS` for COLMAP's own.

    Returns (xyz [N, 3] float32, rgb [N, 3] uint8, info): CPU tensors in the frame and units of
    `cameras.camera_to_worlds`, as the dataparsers' `metadata["points3D_xyz"]` / `["points3D_rgb"]`.
    """
    if len(image_paths) != len(cameras):
        raise ValueError(f"{len(image_paths)} image paths for {len(cameras)} cameras")
    require_pycolmap("triangulation")  # raised, not a message: a caller must not fall back on random points for it
    views = sorted({int(i) for i in indices})
    start = time.perf_counter()
    cameras = cameras.to("cpu")  # the datamanager may hold them on the GPU
    info = TriangulationInfo(ok=False, num_points=0, num_views=len(views), min_points=min_points)
    empty = (torch.zeros((0, 3), dtype=torch.float32), torch.zeros((0, 3), dtype=torch.uint8))
    workspace = existing if existing is not None else TriangulationWorkspace()
    try:
        xyz, rgb = workspace.triangulate(
            cameras, image_paths, views, info, max_image_size=max_image_size, max_exhaustive=max_exhaustive,
            neighbours=neighbours, two_view_tracks=two_view_tracks, num_threads=num_threads, settings=settings,
        )
    except TriangulationError as err:
        info.failed, info.message = True, f"triangulation of {len(views)} views failed: {err}"
        workspace.reset()  # its database may be half-written
        return (*empty, _finish(info, start))
    except Exception as err:  # pycolmap raises RuntimeError/ValueError from COLMAP's checks; one line, no traceback
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        info.failed, info.message = True, f"triangulation of {len(views)} views failed: {type(err).__name__}: {first}"
        workspace.reset()
        return (*empty, _finish(info, start))
    except BaseException:  # interrupted: nothing half-written is reused
        workspace.reset()
        raise
    finally:
        if existing is None:
            workspace.close()
    info.num_points = int(xyz.shape[0])
    info.ok = info.num_points >= min_points
    if not info.ok:
        info.message = (f"only {info.num_points} points triangulated from {len(views)} views (fewer than min_points "
                        f"{min_points}): too few features matched among them")
    return torch.from_numpy(xyz), torch.from_numpy(rgb), _finish(info, start)


def seed_points(cameras, image_paths: Sequence[Path], indices: Sequence[int], **options) -> Optional[Tuple[torch.Tensor, torch.Tensor]]:
    """`triangulate_views`' (xyz, rgb), or None after printing ONE warning line (the count and why) when the caller
    should start from random points instead."""
    from nerfstudio.utils.rich_utils import CONSOLE
    from rich.markup import escape

    xyz, rgb, info = triangulate_views(cameras, image_paths, indices, **options)
    if info.ok:
        return xyz, rgb
    CONSOLE.print(f"[yellow]Seed points: {escape(info.message)}; the splat starts from random points "
                  "(--pipeline.datamanager.seed-points-min sets the fewest to start from)", soft_wrap=True, highlight=False)
    return None


@torch.no_grad()
def away_from_splat(means: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
    """[N] bool: which of the points `xyz` [N, 3] lie farther from every Gaussian mean (`means` [G, 3]) than the
    splat's median nearest-neighbour spacing (`seed-points active` adds only those after a round).

    That spacing is the splat's own sampling density where it has Gaussians (densification keeps it in step with
    the detail the views show): a point closer than it adds nothing the splat lacks, while a point farther lies
    where no Gaussian is, the part of the scene only the new views show. A fixed fraction of the scene's extent
    would ignore densification and the scene's scale (floaters or walls far off stretch the extent)."""
    from scipy.spatial import cKDTree

    means = means.detach().cpu().double().numpy()
    if xyz.shape[0] == 0 or means.shape[0] < 2:
        return torch.ones(xyz.shape[0], dtype=torch.bool)
    tree = cKDTree(means)
    sample = means if means.shape[0] <= 20000 else means[torch.randperm(means.shape[0])[:20000].numpy()]
    spacing = float(np.median(tree.query(sample, k=2)[0][:, 1]))
    distance = tree.query(xyz.detach().cpu().double().numpy(), k=1)[0]
    return torch.from_numpy(distance > spacing)


class TriangulationWorkspace:
    """A temporary folder (images downscaled for SIFT, COLMAP database, triangulation output) kept between calls,
    so a later call extracts only new views and matches only pairs with a new view. Removed by `close()` or at
    the end of a `with` block. `parent`: where the folder is made (default: the system's temp folder)."""

    last_points: Optional[Tuple[np.ndarray, List[List[int]]]] = None
    """The last triangulation's points [N, 3] (as returned) and each one's track: the view indices that see it."""

    def __init__(self, parent: Optional[Path] = None) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="hpgs-triangulate-", dir=parent))
        self._views: Dict[int, tuple] = {}  # view -> (photo path, bytes, mtime, max_image_size)
        self._sizes: Dict[int, Tuple[int, int]] = {}  # view -> (width, height) of its image written here
        self._matched: set = set()  # pairs of views matched already
        self._settings: Optional[TriangulationSettings] = None  # those the kept features and matches were made with

    def __enter__(self) -> TriangulationWorkspace:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)

    def reset(self) -> None:
        """Forget everything (after a failure, or when earlier views changed)."""
        for child in self.root.iterdir() if self.root.is_dir() else []:
            shutil.rmtree(child) if child.is_dir() else child.unlink()
        self._views, self._sizes, self._matched, self._settings = {}, {}, set(), None

    @property
    def images(self) -> Path:
        return self.root / "images"

    @property
    def database(self) -> Path:
        return self.root / "database.db"

    def triangulate(self, cameras, image_paths, views: List[int], info: TriangulationInfo, *, max_image_size: int,
                    max_exhaustive: int, neighbours: int, two_view_tracks: bool, num_threads: int,
                    settings: TriangulationSettings = DEFAULT_SETTINGS) -> Tuple[np.ndarray, np.ndarray]:
        if len(views) < 2:
            raise TriangulationError(f"{len(views)} view(s) given; triangulation needs at least 2")
        bad = [i for i in views if not 0 <= i < len(cameras)]
        if bad:
            raise TriangulationError(f"view index {bad[0]} is out of range (0..{len(cameras) - 1})")
        import pycolmap  # triangulate_views checked it is there
        models = {i: colmap_camera_model(cameras, i) for i in views}

        keys = {i: _file_key(Path(image_paths[i]), max_image_size) for i in views}
        if any(self._views.get(i, keys[i]) != keys[i] for i in views) or set(self._views) - set(views) or \
                (self._settings is not None and self._settings != settings):
            self.reset()  # a photo, the settings changed or a view left: start over rather than mix stale features in
        self._settings = settings
        self.images.mkdir(parents=True, exist_ok=True)
        new = [i for i in views if i not in self._views]
        tick = time.perf_counter()
        for i in new:
            self._sizes[i] = _write_view_image(Path(image_paths[i]), self.images / view_file(i), max_image_size, models[i][1:3])
        info.seconds["images"] = time.perf_counter() - tick

        with _quiet_colmap(pycolmap):
            tick = time.perf_counter()
            if new:
                extraction = pycolmap.FeatureExtractionOptions()
                extraction.num_threads = num_threads
                extraction.max_image_size = max_image_size
                extraction.sift.peak_threshold = settings.peak_threshold
                extraction.sift.max_num_features = settings.max_num_features
                pycolmap.extract_features(self.database, self.images, image_names=[view_file(i) for i in new],
                                          camera_mode=pycolmap.CameraMode.PER_IMAGE, extraction_options=extraction,
                                          device=pycolmap.Device.cpu)
            info.new_views = len(new)
            info.seconds["extract"] = time.perf_counter() - tick

            db_images = self._set_cameras(pycolmap, models)
            missing = [i for i in views if view_file(i) not in db_images]
            if missing:
                raise TriangulationError(f"COLMAP did not read {image_paths[missing[0]]}")
            for i in new:
                self._views[i] = keys[i]

            tick = time.perf_counter()
            pairs = [p for p in view_pairs(cameras, views, max_exhaustive, neighbours) if p not in self._matched]
            if pairs:
                self.match_pairs(pycolmap, cameras, pairs, db_images, settings, num_threads)
                if settings.verification == "poses":
                    info.seconds["match"] = time.perf_counter() - tick
                    tick = time.perf_counter()
                    self._verify_with_poses(pycolmap, cameras, pairs, db_images, settings)
                    info.seconds["verify"] = time.perf_counter() - tick
                self._matched.update(pairs)
            info.pairs_matched = len(pairs)
            info.seconds.setdefault("match", time.perf_counter() - tick)

            tick = time.perf_counter()
            reconstruction = pycolmap.Reconstruction()
            for i in views:
                image_id, camera = db_images[view_file(i)]
                reconstruction.add_camera_with_trivial_rig(camera)
                image = pycolmap.Image(name=view_file(i), camera_id=camera.camera_id, image_id=image_id)
                reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(colmap_cam_from_world(cameras.camera_to_worlds[i])))
            options = pycolmap.IncrementalPipelineOptions()
            options.triangulation.ignore_two_view_tracks = not two_view_tracks
            options.min_num_matches = settings.min_num_inliers
            options.num_threads = num_threads
            out = self.root / "triangulated"
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            result = pycolmap.triangulate_points(reconstruction, self.database, self.images, out, options=options)
            info.seconds["triangulate"] = time.perf_counter() - tick

        points = list(result.points3D.values())
        xyz = np.array([p.xyz for p in points], dtype=np.float32).reshape(-1, 3)
        rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
        keep = np.isfinite(xyz).all(1)
        # which views see each kept point (its track), for what supervises views with these points (the depth loss)
        names = {image_id: view_index(image.name) for image_id, image in result.images.items()}
        tracks = [sorted({names[e.image_id] for e in p.track.elements if e.image_id in names}) for p in points]
        self.last_points = (xyz[keep], [t for t, k in zip(tracks, keep) if k])
        if points:
            info.mean_track_length = float(result.compute_mean_track_length())
            info.mean_reprojection_error = float(result.compute_mean_reprojection_error())
        return xyz[keep], rgb[keep]

    def match_pairs(self, pycolmap, cameras, pairs: List[Tuple[int, int]], db_images: Dict[str, Tuple[int, object]],
                    settings: TriangulationSettings, num_threads: int) -> None:
        """Write these pairs' feature matches into the database: COLMAP's matcher (ratio test `settings.max_ratio`)
        and, for "ransac", COLMAP's two-view geometry (its inlier matches); "poses" verifies them after this.
        The one seam for another matcher: a subclass overrides it (one that verifies its own matches writes inlier
        matches itself). `db_images`: view file name -> (image id, pycolmap Camera)."""
        pair_file = self.root / "pairs.txt"
        pair_file.write_text("".join(f"{view_file(a)} {view_file(b)}\n" for a, b in pairs))
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        matching.sift.max_ratio = settings.max_ratio
        matching.skip_geometric_verification = settings.verification == "poses"  # the known poses verify instead
        verification = pycolmap.TwoViewGeometryOptions()
        verification.min_num_inliers = settings.min_num_inliers
        pycolmap.match_image_pairs(self.database, matching_options=matching,
                                   pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pair_file)),
                                   verification_options=verification, device=pycolmap.Device.cpu)

    def _verify_with_poses(self, pycolmap, cameras, pairs, db_images, settings: TriangulationSettings) -> None:
        """Each pair's two-view geometry from its KNOWN relative pose: the matches within
        `settings.max_epipolar_error` pixels of their epipolar lines (both ways), written as the pair's inlier
        matches when there are at least `settings.min_num_inliers`, instead of COLMAP's RANSAC estimate."""
        database = pycolmap.Database.open(self.database)
        try:
            for a, b in pairs:
                (id1, camera1), (id2, camera2) = db_images[view_file(a)], db_images[view_file(b)]
                matches = database.read_matches(id1, id2)
                if len(matches) == 0:
                    continue
                cam2_from_cam1 = relative_pose(cameras.camera_to_worlds[a], cameras.camera_to_worlds[b])
                points1 = database.read_keypoints(id1)[matches[:, 0], :2].astype(np.float64)
                points2 = database.read_keypoints(id2)[matches[:, 1], :2].astype(np.float64)
                error = epipolar_distance(camera1, camera2, cam2_from_cam1, points1, points2)
                inliers = matches[error < settings.max_epipolar_error]
                if len(inliers) >= settings.min_num_inliers:
                    write_known_pose_geometry(pycolmap, database, id1, id2, inliers, cam2_from_cam1)
        finally:
            database.close()

    def _set_cameras(self, pycolmap, models) -> Dict[str, Tuple[int, object]]:
        """Give each view's database camera its known intrinsics at the downscaled size (extraction made a guess);
        the matcher's geometric verification then uses them. Returns name -> (image id, camera)."""
        found = {}
        database = pycolmap.Database.open(self.database)
        try:
            for image in database.read_all_images():
                view = view_index(image.name)
                if view not in models:
                    continue
                model, width, height, params = models[view]
                w, h = self._sizes[view]
                sx, sy = w / width, h / height
                params = list(params)
                params[0], params[1], params[2], params[3] = params[0] * sx, params[1] * sy, params[2] * sx, params[3] * sy
                camera = pycolmap.Camera(model=model, width=w, height=h, params=params, camera_id=image.camera_id)
                camera.has_prior_focal_length = True
                database.update_camera(camera)
                found[image.name] = (image.image_id, camera)
        finally:
            database.close()
        return found


def view_file(view: int) -> str:
    """A view's image name in the workspace: its index (photo names can repeat, e.g. Blender's train/ and test/)."""
    return f"{view:06d}.png"


def view_index(name: str) -> int:
    return int(Path(name).stem)


def colmap_camera_model(cameras, i: int) -> Tuple[str, int, int, List[float]]:
    """(COLMAP model name, width, height, params) of nerfstudio camera `i`, at the camera's own size.

    nerfstudio's PERSPECTIVE distortion is [k1, k2, k3, k4, p1, p2] with radial 1 + k1 r^2 + k2 r^4 + k3 r^6
    + k4 r^8: OPENCV when k3 = k4 = 0, else FULL_OPENCV (rational; k3 maps exactly, an r^8 term k4 has no COLMAP
    equivalent and is dropped). FISHEYE is OPENCV_FISHEYE (k1..k4 on theta). Other types: TriangulationError."""
    from nerfstudio.cameras.cameras import CameraType

    kind = CameraType(int(cameras.camera_type[i].item()))
    fx, fy, cx, cy = (float(getattr(cameras, name)[i].item()) for name in ("fx", "fy", "cx", "cy"))
    width, height = int(cameras.width[i].item()), int(cameras.height[i].item())
    d = [0.0] * 6 if cameras.distortion_params is None else [float(v) for v in cameras.distortion_params[i].reshape(-1)[:6]]
    k1, k2, k3, k4, p1, p2 = d
    if kind == CameraType.PERSPECTIVE:
        if not any(d):
            return "PINHOLE", width, height, [fx, fy, cx, cy]
        if k3 == 0 and k4 == 0:
            return "OPENCV", width, height, [fx, fy, cx, cy, k1, k2, p1, p2]
        return "FULL_OPENCV", width, height, [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    if kind == CameraType.FISHEYE:
        return "OPENCV_FISHEYE", width, height, [fx, fy, cx, cy, k1, k2, k3, k4]
    raise TriangulationError(f"camera {i} is {kind.name}; only PERSPECTIVE and FISHEYE cameras can be triangulated")


def colmap_cam_from_world(camera_to_world) -> np.ndarray:
    """[3, 4] COLMAP world-to-camera (x right, y down, z forward) from a nerfstudio camera-to-world [3, 4] (x right,
    y up, z back), in the same world frame: flip the camera's y and z axes, then invert the rigid transform."""
    c2w = np.asarray(camera_to_world, dtype=np.float64)[:3, :4]
    rotation = c2w[:, :3] * np.array([1.0, -1.0, -1.0])  # columns: the camera's axes in the world
    rotation_cw = rotation.T
    return np.concatenate([rotation_cw, (-rotation_cw @ c2w[:, 3])[:, None]], axis=1)


def write_known_pose_geometry(pycolmap, database, id1: int, id2: int, inliers: np.ndarray, cam2_from_cam1: np.ndarray) -> None:
    """Store a pair's two-view geometry from its KNOWN relative pose, with these inlier matches [K, 2], in place of
    any COLMAP estimated (the triangulator reads only inlier matches)."""
    geometry = pycolmap.TwoViewGeometry(
        config=pycolmap.TwoViewGeometryConfiguration.CALIBRATED, inlier_matches=inliers.astype(np.uint32),
        E=essential_matrix(cam2_from_cam1), cam2_from_cam1=pycolmap.Rigid3d(cam2_from_cam1))
    if database.exists_two_view_geometry(id1, id2):
        database.update_two_view_geometry(id1, id2, geometry)
    else:
        database.write_two_view_geometry(id1, id2, geometry)


def relative_pose(camera_to_world1, camera_to_world2) -> np.ndarray:
    """[3, 4] COLMAP cam2_from_cam1 (x right, y down, z forward) between two nerfstudio camera-to-worlds [3, 4]."""
    pose1, pose2 = colmap_cam_from_world(camera_to_world1), colmap_cam_from_world(camera_to_world2)
    rotation = pose2[:, :3] @ pose1[:, :3].T
    return np.concatenate([rotation, (pose2[:, 3] - rotation @ pose1[:, 3])[:, None]], axis=1)


def essential_matrix(cam2_from_cam1: np.ndarray) -> np.ndarray:
    """E = [t]x R: x2^T E x1 = 0 for normalised (undistorted, unit focal) points x1, x2 of one 3D point."""
    t = cam2_from_cam1[:, 3]
    cross = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return cross @ cam2_from_cam1[:, :3]


def normalised_rays(camera, points: np.ndarray) -> np.ndarray:
    """[M, 3] homogeneous normalised (undistorted, unit focal) coordinates of pixels [M, 2] of a pycolmap `Camera`."""
    out = np.asarray(camera.cam_from_img(np.asarray(points, dtype=np.float64).reshape(-1, 2)), dtype=np.float64).reshape(-1, 2)
    return np.concatenate([out, np.ones((len(out), 1))], axis=1)


def epipolar_lines(camera1, camera2, cam2_from_cam1: np.ndarray, points1: np.ndarray, points2: np.ndarray):
    """The pieces of the epipolar distance: the normalised rays x2 [M2, 3] of points2, the epipolar lines in image 2
    of points1 [M1, 3], and the factors [M1] and [M2] that turn a residual x2 . line2 into pixels in image 2 and in
    image 1 (mean focal length over the line's normal length; inf where a line has no direction)."""
    x1, x2 = normalised_rays(camera1, points1), normalised_rays(camera2, points2)
    e = essential_matrix(cam2_from_cam1)
    line2, line1 = x1 @ e.T, x2 @ e  # epipolar lines in image 2 (of x1) and in image 1 (of x2)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale2 = camera2.mean_focal_length() / np.linalg.norm(line2[:, :2], axis=1)
        scale1 = camera1.mean_focal_length() / np.linalg.norm(line1[:, :2], axis=1)
    return x2, line2, scale2, scale1


def epipolar_distance(camera1, camera2, cam2_from_cam1: np.ndarray, points1: np.ndarray, points2: np.ndarray) -> np.ndarray:
    """[M] for matched pixels points1 [M, 2] (camera1) and points2 [M, 2] (camera2), pycolmap `Camera`s: the larger
    of the two distances, in pixels, between a point and the epipolar line of its match under the known relative
    pose (lens distortion removed first; a normalised distance times the camera's mean focal length). Points
    that cannot be undistorted are infinitely far."""
    x2, line2, scale2, scale1 = epipolar_lines(camera1, camera2, cam2_from_cam1, points1, points2)
    with np.errstate(invalid="ignore"):
        residual = np.abs((x2 * line2).sum(1))
        distance = np.maximum(residual * scale2, residual * scale1)
    return np.where(np.isfinite(distance), distance, np.inf)


def view_pairs(cameras, views: List[int], max_exhaustive: int, neighbours: int) -> List[Tuple[int, int]]:
    """Pairs (a < b) to match: all of them up to `max_exhaustive` views, else each view with its `neighbours`
    nearest by camera centre (cameras facing away from each other, > 90 degrees, are skipped)."""
    if len(views) <= max_exhaustive:
        return [(a, b) for k, a in enumerate(views) for b in views[k + 1:]]
    c2w = cameras.camera_to_worlds[torch.tensor(views)].double().numpy()
    centres, forward = c2w[:, :, 3], -c2w[:, :, 2]
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    distance[forward @ forward.T < 0] = np.inf
    np.fill_diagonal(distance, np.inf)
    pairs = set()
    for k in range(len(views)):
        for m in np.argsort(distance[k])[:neighbours]:
            if np.isfinite(distance[k, m]):
                pairs.add((min(views[k], views[m]), max(views[k], views[m])))
    return sorted(pairs)


def _file_key(path: Path, max_image_size: int) -> Tuple[str, int, float, int]:
    try:
        stat = path.stat()
    except OSError as err:
        raise TriangulationError(f"cannot read {path} ({err.strerror})") from err
    return str(path), stat.st_size, stat.st_mtime, max_image_size


def _write_view_image(source: Path, target: Path, max_image_size: int, camera_size: Tuple[int, int]) -> Tuple[int, int]:
    """Write `source` as an RGB PNG, downscaled so its longer side is at most `max_image_size` (never upscaled),
    through a temp file and a rename; returns its (width, height). Its aspect ratio must be its camera's."""
    width, height = camera_size
    try:
        with Image.open(source) as image:
            if abs(image.width * height - image.height * width) > 0.01 * width * height:
                raise TriangulationError(f"{source} is {image.width}x{image.height} but its camera says {width}x{height}")
            scale = min(1.0, max_image_size / max(image.size))
            size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
            if image.mode in ("RGBA", "LA") or (image.mode == "P" and "transparency" in image.info):
                rgba = image.convert("RGBA")
                image = Image.alpha_composite(Image.new("RGBA", rgba.size, (255, 255, 255, 255)), rgba)  # Blender's white
            image = image.convert("RGB")
            if image.size != size:
                image = image.resize(size, Image.Resampling.LANCZOS)
            tmp = target.with_name(f".{target.name}.tmp.png")
            image.save(tmp, compress_level=1)  # written once, read once: speed over size
            os.replace(tmp, target)
    except (OSError, SyntaxError, ValueError) as err:  # PIL's errors for unreadable files
        raise TriangulationError(f"cannot read {source} ({err})") from err
    return size


@contextlib.contextmanager
def _quiet_colmap(pycolmap) -> Iterator[None]:
    """COLMAP logs every step to stderr: only its errors are shown while it runs."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def _finish(info: TriangulationInfo, start: float) -> TriangulationInfo:
    info.seconds["total"] = time.perf_counter() - start
    info.seconds = {k: round(v, 3) for k, v in info.seconds.items()}
    return info

