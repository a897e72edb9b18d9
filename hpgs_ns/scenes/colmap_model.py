"""A scene's COLMAP model (`sparse/0`), binary or text, read and rewritten with nerfstudio's own parsers.

nerfstudio's dataparser reads poses and seed points with these parsers, so image ids and point order line up
with what it trains on; they are pure Python, so stress copies can be made where pycolmap (a 38 MB wheel) is
not installed, such as the lent GPU machine. pycolmap still writes whole new reconstructions (synthetic scenes).
nerfstudio's `read_model` would do the format detection but prints and returns None on a missing file.

Binary files are read here, into nerfstudio's named tuples, with every count checked against the bytes left:
nerfstudio's binary readers raise `struct.error` on a truncated file and, for a corrupt count, ask for gigabytes.
A file that cannot be read is a one-line `ColmapModelError` naming it (`read_model_file`, `check_model`).
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Tuple

import numpy as np
from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils

from hpgs_ns.atomic_write import atomic_path
from hpgs_ns.errors import UserError

# COLMAP >= 3.12 (pycolmap 4) also stores poses in rigs/frames; a rewritten images file makes those stale.
RIG_FILES = ("rigs", "frames")


def model_file(model_dir: Path, stem: str) -> Optional[Path]:
    """`model_dir/<stem>.bin`, else `<stem>.txt`, else None."""
    for ext in (".bin", ".txt"):
        path = Path(model_dir) / f"{stem}{ext}"
        if path.exists():
            return path
    return None


class ColmapModelError(UserError, ValueError):
    """A COLMAP model file that cannot be read (truncated, corrupt, not a COLMAP file)."""


class _Bytes:
    """A binary file's bytes read front to back; `ValueError`s say what is wrong."""

    def __init__(self, data: bytes):
        self.data, self.at = data, 0

    def unpack(self, fmt: str) -> Tuple[Any, ...]:
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.data):
            raise ValueError(f"ends after {len(self.data)} bytes, in the middle of a record")
        values = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return values

    def count(self, each: int) -> int:
        """A uint64 count of records of at least `each` bytes, checked against the bytes left after it (a count
        inside the file, e.g. an image's keypoints, counts what follows it, not the whole file)."""
        at = self.at
        (n,) = self.unpack("Q")
        left = len(self.data) - self.at
        if n * each > left:
            raise ValueError(f"a count at byte {at} says {n} records of at least {each} bytes follow, but only {left} of "
                             f"its {len(self.data)} bytes are left")
        return n

    def array(self, n: int, dtype: np.dtype) -> np.ndarray:
        dtype = np.dtype(dtype)
        end = self.at + n * dtype.itemsize
        if end > len(self.data):
            raise ValueError(f"ends after {len(self.data)} bytes, in the middle of a record")
        out = np.frombuffer(self.data, dtype=dtype, count=n, offset=self.at)
        self.at = end
        return out

    def name(self) -> str:
        end = self.data.find(b"\x00", self.at)
        if end < 0:
            raise ValueError("ends inside an image name")
        text = self.data[self.at:end].decode("utf-8")
        self.at = end + 1
        return text

    def done(self) -> None:
        if self.at != len(self.data):
            raise ValueError(f"has {len(self.data) - self.at} bytes after its last record")


def _cameras_binary(data: _Bytes) -> Dict[int, colmap_utils.Camera]:
    cameras = {}
    for _ in range(data.count(24)):
        camera_id, model_id, width, height = data.unpack("iiQQ")
        model = colmap_utils.CAMERA_MODEL_IDS.get(model_id)
        if model is None:
            raise ValueError(f"camera {camera_id} has an unknown camera model id {model_id}")
        params = np.array(data.unpack("d" * model.num_params))
        cameras[camera_id] = colmap_utils.Camera(id=camera_id, model=model.model_name, width=width, height=height,
                                                 params=params)
    return cameras


def _images_binary(data: _Bytes) -> Dict[int, colmap_utils.Image]:
    images = {}
    for _ in range(data.count(64 + 1 + 8)):
        image_id, *pose, camera_id = data.unpack("idddddddi")
        name = data.name()
        points = data.array(data.count(24), np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]))
        images[image_id] = colmap_utils.Image(
            id=image_id, qvec=np.array(pose[:4]), tvec=np.array(pose[4:]), camera_id=camera_id, name=name,
            xys=np.column_stack([points["x"].astype(float), points["y"].astype(float)]),
            point3D_ids=points["id"].astype(np.int64))
    return images


def _points3D_binary(data: _Bytes) -> Dict[int, colmap_utils.Point3D]:
    points = {}
    for _ in range(data.count(43 + 8)):
        point_id, x, y, z, r, g, b, error = data.unpack("QdddBBBd")
        track = data.array(data.count(8), np.dtype([("image", "<i4"), ("point2D", "<i4")]))
        points[point_id] = colmap_utils.Point3D(
            id=point_id, xyz=np.array((x, y, z)), rgb=np.array((r, g, b)), error=np.array(error),
            image_ids=track["image"].astype(np.int64), point2D_idxs=track["point2D"].astype(np.int64))
    return points


def _binary(parse: Callable[[_Bytes], Dict]) -> Callable[[Path], Dict]:
    def read(path: Path) -> Dict:
        data = _Bytes(Path(path).read_bytes())
        out = parse(data)
        data.done()
        return out

    return read


READERS: Dict[Tuple[str, str], Callable[[Path], Dict]] = {
    ("cameras", ".bin"): _binary(_cameras_binary),
    ("images", ".bin"): _binary(_images_binary),
    ("points3D", ".bin"): _binary(_points3D_binary),
    ("cameras", ".txt"): colmap_utils.read_cameras_text,
    ("images", ".txt"): colmap_utils.read_images_text,
    ("points3D", ".txt"): colmap_utils.read_points3D_text,
}


def read_model_file(path: Path) -> Dict:
    """A COLMAP `cameras`, `images` or `points3D` file (.bin or .txt) as nerfstudio's parsers return it (id ->
    named tuple); `ColmapModelError` naming the file for one that cannot be read."""
    path = Path(path)
    reader = READERS.get((path.stem, path.suffix))
    if reader is None:
        raise ColmapModelError(f"{path} is not a COLMAP model file (cameras, images or points3D, .bin or .txt)")
    try:
        return reader(path)
    except Exception as err:  # struct, unicode, value, index and key errors: a damaged file, whichever it is
        why = f"{type(err).__name__}: {str(err).splitlines()[0][:120]}" if str(err) else type(err).__name__
        raise ColmapModelError(f"{path} is not a readable COLMAP {path.stem} file ({why}); it is truncated or damaged: "
                               "restore it from the source or re-run COLMAP") from err


def check_model(model_dir: Path, points: bool = True) -> None:
    """Read the model's cameras, images and (with `points`) points3D files, raising `ColmapModelError` for the
    first that cannot be read (a missing file is the caller's to report)."""
    for stem in ("cameras", "images") + (("points3D",) if points else ()):
        path = model_file(model_dir, stem)
        if path is not None:
            read_model_file(path)


def read_images(model_dir: Path) -> Optional[Dict[int, colmap_utils.Image]]:
    """image id -> COLMAP Image (name, qvec, tvec, ...); None when the model has no images file."""
    path = model_file(model_dir, "images")
    return None if path is None else read_model_file(path)


def read_points3D(model_dir: Path) -> Optional[Dict[int, colmap_utils.Point3D]]:
    """point id -> COLMAP Point3D (xyz, rgb, track image ids, ...), in file order; None without a points file."""
    path = model_file(model_dir, "points3D")
    return None if path is None else read_model_file(path)


def camera_pose(image: colmap_utils.Image) -> Tuple[np.ndarray, np.ndarray]:
    """(cam_from_world rotation R [3, 3], camera centre [3]) of a COLMAP image, which stores x_cam = R x + t:
    the centre is -R^T t."""
    rotation = colmap_utils.qvec2rotmat(image.qvec)
    return rotation, -rotation.T @ image.tvec


def write_images(model_dir: Path, images: Dict[int, colmap_utils.Image]) -> Path:
    """Replace the model's images file (same format; binary when there is none) atomically, and drop rig/frame
    files, whose poses would now disagree (COLMAP rebuilds trivial rigs from the images when they are absent)."""
    path = model_file(model_dir, "images") or Path(model_dir) / "images.bin"
    writer = colmap_utils.write_images_binary if path.suffix == ".bin" else colmap_utils.write_images_text
    with atomic_path(path) as tmp:
        writer(images, tmp)
    for stem in RIG_FILES:
        for ext in (".bin", ".txt"):
            (Path(model_dir) / f"{stem}{ext}").unlink(missing_ok=True)
    return path
