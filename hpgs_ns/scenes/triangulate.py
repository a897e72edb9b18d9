"""Seed points triangulated from the active views only, at their known poses: no test photo is ever used.

splatfacto's seed points usually come from the capture's COLMAP model, which was built from every photo,
test photos included (a leak), and which a capture in progress does not have at all (nerfstudio-data, Blender).
Here pycolmap extracts SIFT features (CPU) from the given views, matches them among themselves (every pair up
to `max_exhaustive` views, else each view with its nearest views by camera centre), and triangulates with the
poses held fixed, so the points are in the cameras' own frame: nerfstudio's normalised (auto-oriented, scaled)
frame, the frame of `cameras.camera_to_worlds`, in its units.

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


class TriangulationError(UserError):
    """Triangulation could not run (pycolmap missing or failing, an unreadable image, a camera type COLMAP lacks).
    `triangulate_views` returns it as `info.message` instead of raising; `TriangulationInfo.raise_if_failed` raises."""


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

    Returns (xyz [N, 3] float32, rgb [N, 3] uint8, info): CPU tensors in the frame and units of
    `cameras.camera_to_worlds`, as the dataparsers' `metadata["points3D_xyz"]` / `["points3D_rgb"]`.
    """
    if len(image_paths) != len(cameras):
        raise ValueError(f"{len(image_paths)} image paths for {len(cameras)} cameras")
    views = sorted({int(i) for i in indices})
    start = time.perf_counter()
    cameras = cameras.to("cpu")  # the datamanager may hold them on the GPU
    info = TriangulationInfo(ok=False, num_points=0, num_views=len(views), min_points=min_points)
    empty = (torch.zeros((0, 3), dtype=torch.float32), torch.zeros((0, 3), dtype=torch.uint8))
    workspace = existing if existing is not None else TriangulationWorkspace()
    try:
        xyz, rgb = workspace.triangulate(
            cameras, image_paths, views, info, max_image_size=max_image_size, max_exhaustive=max_exhaustive,
            neighbours=neighbours, two_view_tracks=two_view_tracks, num_threads=num_threads,
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
    CONSOLE.print(f"[yellow]Seed points: {escape(info.message)}; the splat starts from random points", soft_wrap=True, highlight=False)
    return None


class TriangulationWorkspace:
    """A temporary folder (images downscaled for SIFT, COLMAP database, triangulation output) kept between calls,
    so a later call extracts only new views and matches only pairs with a new view. Removed by `close()` or at
    the end of a `with` block. `parent`: where the folder is made (default: the system's temp folder)."""

    def __init__(self, parent: Optional[Path] = None) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="hpgs-triangulate-", dir=parent))
        self._views: Dict[int, tuple] = {}  # view -> (photo path, bytes, mtime, max_image_size)
        self._sizes: Dict[int, Tuple[int, int]] = {}  # view -> (width, height) of its image written here
        self._matched: set = set()  # pairs of views matched already

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
        self._views, self._sizes, self._matched = {}, {}, set()

    @property
    def images(self) -> Path:
        return self.root / "images"

    @property
    def database(self) -> Path:
        return self.root / "database.db"

    def triangulate(self, cameras, image_paths, views: List[int], info: TriangulationInfo, *, max_image_size: int,
                    max_exhaustive: int, neighbours: int, two_view_tracks: bool, num_threads: int) -> Tuple[np.ndarray, np.ndarray]:
        if len(views) < 2:
            raise TriangulationError(f"{len(views)} view(s) given; triangulation needs at least 2")
        bad = [i for i in views if not 0 <= i < len(cameras)]
        if bad:
            raise TriangulationError(f"view index {bad[0]} is out of range (0..{len(cameras) - 1})")
        try:
            import pycolmap
        except ImportError as err:
            raise TriangulationError("pycolmap is not installed (pip install pycolmap)") from err
        models = {i: colmap_camera_model(cameras, i) for i in views}

        keys = {i: _file_key(Path(image_paths[i]), max_image_size) for i in views}
        if any(self._views.get(i, keys[i]) != keys[i] for i in views) or set(self._views) - set(views):
            self.reset()  # a photo changed or a view left: start over rather than mix stale features in
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
                pair_file = self.root / "pairs.txt"
                pair_file.write_text("".join(f"{view_file(a)} {view_file(b)}\n" for a, b in pairs))
                matching = pycolmap.FeatureMatchingOptions()
                matching.num_threads = num_threads
                pycolmap.match_image_pairs(self.database, matching_options=matching,
                                           pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pair_file)),
                                           device=pycolmap.Device.cpu)
                self._matched.update(pairs)
            info.pairs_matched = len(pairs)
            info.seconds["match"] = time.perf_counter() - tick

            tick = time.perf_counter()
            reconstruction = pycolmap.Reconstruction()
            for i in views:
                image_id, camera = db_images[view_file(i)]
                reconstruction.add_camera_with_trivial_rig(camera)
                image = pycolmap.Image(name=view_file(i), camera_id=camera.camera_id, image_id=image_id)
                reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(colmap_cam_from_world(cameras.camera_to_worlds[i])))
            options = pycolmap.IncrementalPipelineOptions()
            options.triangulation.ignore_two_view_tracks = not two_view_tracks
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
        if points:
            info.mean_track_length = float(result.compute_mean_track_length())
            info.mean_reprojection_error = float(result.compute_mean_reprojection_error())
        return xyz[keep], rgb[keep]

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

