"""A scene's COLMAP model (`sparse/0`), binary or text, read and rewritten with nerfstudio's own parsers.

nerfstudio's dataparser reads poses and seed points with these parsers, so image ids and point order line up
with what it trains on; they are pure Python, so stress copies can be made where pycolmap (a 38 MB wheel) is
not installed, such as the lent GPU machine. pycolmap still writes whole new reconstructions (synthetic scenes).
nerfstudio's `read_model` would do the format detection but prints and returns None on a missing file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional, Tuple

import numpy as np
from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils

from hpgs_ns.atomic_write import atomic_path

# COLMAP >= 3.12 (pycolmap 4) also stores poses in rigs/frames; a rewritten images file makes those stale.
RIG_FILES = ("rigs", "frames")


def model_file(model_dir: Path, stem: str) -> Optional[Path]:
    """`model_dir/<stem>.bin`, else `<stem>.txt`, else None."""
    for ext in (".bin", ".txt"):
        path = Path(model_dir) / f"{stem}{ext}"
        if path.exists():
            return path
    return None


def read_images(model_dir: Path) -> Optional[Dict[int, colmap_utils.Image]]:
    """image id -> COLMAP Image (name, qvec, tvec, ...); None when the model has no images file."""
    path = model_file(model_dir, "images")
    if path is None:
        return None
    return colmap_utils.read_images_binary(path) if path.suffix == ".bin" else colmap_utils.read_images_text(path)


def read_points3D(model_dir: Path) -> Optional[Dict[int, colmap_utils.Point3D]]:
    """point id -> COLMAP Point3D (xyz, rgb, track image ids, ...), in file order; None without a points file."""
    path = model_file(model_dir, "points3D")
    if path is None:
        return None
    return colmap_utils.read_points3D_binary(path) if path.suffix == ".bin" else colmap_utils.read_points3D_text(path)


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
