"""The triangulation variants a study rejected (benchmarks/triangulation_yield.py, docs/lab/triangulation-yield.md),
kept here so the benchmark can still measure them; hpgs_ns.scenes.triangulate runs only "ransac" and "poses".

- guided matching (`verification="guided"`): the known pose guides the matching itself: each feature is matched
  (ratio test, cross-check) only among the features of the other view within `max_epipolar_error` pixels of its
  epipolar line, so wide-baseline pairs whose matches fail the ratio test against the whole image still match.
  Plugged in by overriding `TriangulationWorkspace.match_pairs`.
- upsampled photos (`upscale_to`): photos whose longer side is below `upscale_to` pixels are upsampled to it
  (bicubic) before SIFT, the rest downscaled to `max_image_size` as usual. Done on copies of the photos before
  the call, which then lets SIFT see them at up to `upscale_to`.

    xyz, rgb, info = triangulate_variant(cameras, image_paths, views, VariantSettings(verification="guided"))
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np
from PIL import Image

from hpgs_ns.scenes.triangulate import (
    DEFAULT_MAX_IMAGE_SIZE,
    TriangulationSettings,
    TriangulationWorkspace,
    epipolar_lines,
    relative_pose,
    triangulate_views,
    view_file,
    write_known_pose_geometry,
)


@dataclasses.dataclass(frozen=True)
class VariantSettings(TriangulationSettings):
    """`TriangulationSettings` plus the rejected variants: `verification` may also be "guided" (the known pose
    guides the matching; `max_epipolar_error`, `max_ratio` and `min_num_inliers` as for "poses"), and
    upscale_to: photos whose longer side is below this (pixels) are upsampled to it before SIFT (0: never)."""

    upscale_to: int = 0

    def __post_init__(self) -> None:
        if self.verification != "guided":
            super().__post_init__()


class VariantWorkspace(TriangulationWorkspace):
    """A workspace whose matcher is guided by the known poses when `settings.verification == "guided"`; the
    package's own matcher otherwise."""

    def match_pairs(self, pycolmap, cameras, pairs: List[Tuple[int, int]], db_images: Dict[str, Tuple[int, object]],
                    settings: TriangulationSettings, num_threads: int) -> None:
        """Match each pair among the features near their epipolar lines under the KNOWN relative pose
        (`guided_matches`); the matches are written both as the pair's matches and as its inlier matches."""
        if settings.verification != "guided":
            super().match_pairs(pycolmap, cameras, pairs, db_images, settings, num_threads)
            return
        database = pycolmap.Database.open(self.database)
        features: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}

        def read(image_id):
            if image_id not in features:
                points = database.read_keypoints(image_id)[:, :2].astype(np.float64)
                features[image_id] = (points, np.asarray(database.read_descriptors(image_id).data))
            return features[image_id]

        try:
            for a, b in pairs:
                (id1, camera1), (id2, camera2) = db_images[view_file(a)], db_images[view_file(b)]
                (points1, descriptors1), (points2, descriptors2) = read(id1), read(id2)
                cam2_from_cam1 = relative_pose(cameras.camera_to_worlds[a], cameras.camera_to_worlds[b])
                distance = epipolar_distance_matrix(camera1, camera2, cam2_from_cam1, points1, points2)
                matches = guided_matches(descriptors1, descriptors2, distance, settings.max_epipolar_error, settings.max_ratio)
                database.write_matches(id1, id2, matches)
                if len(matches) >= settings.min_num_inliers:
                    write_known_pose_geometry(pycolmap, database, id1, id2, matches, cam2_from_cam1)
        finally:
            database.close()


def triangulate_variant(cameras, image_paths: Sequence[Path], views: Sequence[int], settings: TriangulationSettings,
                        max_image_size: int = DEFAULT_MAX_IMAGE_SIZE):
    """`triangulate_views` (one call, a temporary workspace) with a variant's settings: (xyz, rgb, info). The
    upsampling, when `settings.upscale_to`, is counted in `info.seconds["images"]` and `["total"]`."""
    upscale_to = getattr(settings, "upscale_to", 0)
    with tempfile.TemporaryDirectory(prefix="hpgs-upsampled-") as folder, VariantWorkspace() as workspace:
        start = time.perf_counter()
        if upscale_to:
            image_paths = upsampled_photos(image_paths, views, Path(folder), upscale_to, max_image_size)
            max_image_size = max(max_image_size, upscale_to)  # the package then writes them as they are, SIFT sees them so
        prepared = time.perf_counter() - start
        xyz, rgb, info = triangulate_views(cameras, image_paths, views, max_image_size=max_image_size, existing=workspace,
                                           settings=settings)
    if upscale_to:
        for stage in ("images", "total"):
            info.seconds[stage] = round(info.seconds.get(stage, 0.0) + prepared, 3)
    return xyz, rgb, info


def upsampled_photos(image_paths: Sequence[Path], views: Sequence[int], folder: Path, upscale_to: int,
                     max_image_size: int) -> List[Path]:
    """`image_paths` with the photos of `views` replaced by RGB PNG copies in `folder`: upsampled (bicubic) so their
    longer side is `upscale_to` when it is shorter, else downscaled (Lanczos) to at most `max_image_size`;
    RGBA put on white, as the package does."""
    paths = [Path(p) for p in image_paths]
    for i in sorted({int(v) for v in views}):
        with Image.open(paths[i]) as image:
            longest = max(image.size)
            scale = upscale_to / longest if longest < upscale_to else min(1.0, max_image_size / longest)
            size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
            if image.mode in ("RGBA", "LA") or (image.mode == "P" and "transparency" in image.info):
                rgba = image.convert("RGBA")
                image = Image.alpha_composite(Image.new("RGBA", rgba.size, (255, 255, 255, 255)), rgba)
            image = image.convert("RGB")
            if image.size != size:
                image = image.resize(size, Image.Resampling.LANCZOS if scale < 1 else Image.Resampling.BICUBIC)
            paths[i] = folder / view_file(i)
            image.save(paths[i], compress_level=1)
    return paths


def epipolar_distance_matrix(camera1, camera2, cam2_from_cam1: np.ndarray, points1: np.ndarray,
                             points2: np.ndarray) -> np.ndarray:
    """[M1, M2]: `hpgs_ns.scenes.triangulate.epipolar_distance` for every point of points1 [M1, 2] (camera1) with
    every point of points2 [M2, 2] (camera2): pixels, the larger of the two point-to-epipolar-line distances."""
    x2, line2, scale2, scale1 = epipolar_lines(camera1, camera2, cam2_from_cam1, points1, points2)
    with np.errstate(invalid="ignore"):
        residual = np.abs(line2 @ x2.T)  # [M1, M2]: x2_j . (E x1_i)
        distance = np.maximum(residual * scale2[:, None], residual * scale1[None, :])
    return np.where(np.isfinite(distance), distance, np.inf)


def guided_matches(descriptors1: np.ndarray, descriptors2: np.ndarray, distance: np.ndarray, max_error: float,
                   max_ratio: float, max_descriptor_distance: float = 0.7) -> np.ndarray:
    """[K, 2] matches (index in 1, index in 2) between SIFT descriptors [M1, 128] and [M2, 128] among the pairs
    whose epipolar `distance` [M1, M2] (pixels) is below `max_error`: each feature's nearest descriptor among
    those candidates only, kept when it passes the ratio test against the second nearest candidate (none: passes),
    is within `max_descriptor_distance` (the angle between the descriptors, radians, as COLMAP's matcher) and is
    mutual (cross-checked)."""
    if len(descriptors1) == 0 or len(descriptors2) == 0:
        return np.zeros((0, 2), dtype=np.uint32)
    d1 = descriptors1.astype(np.float32)
    d2 = descriptors2.astype(np.float32)
    d1 /= np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), 1e-12)
    d2 /= np.maximum(np.linalg.norm(d2, axis=1, keepdims=True), 1e-12)
    similarity = d1 @ d2.T
    similarity[~(distance < max_error)] = -1.0  # outside the epipolar band: never a candidate
    angle = np.arccos(np.clip(similarity, -1.0, 1.0))

    def best(angles):  # per row: (index of the nearest, its angle, the second nearest's angle)
        if angles.shape[1] == 1:
            return np.zeros(len(angles), dtype=np.int64), angles[:, 0], np.full(len(angles), np.pi)
        two = np.argpartition(angles, 1, axis=1)[:, :2]
        a = np.take_along_axis(angles, two, axis=1)
        order = np.argsort(a, axis=1)
        return np.take_along_axis(two, order, 1)[:, 0], np.take_along_axis(a, order, 1)[:, 0], np.take_along_axis(a, order, 1)[:, 1]

    forward, angle1, second1 = best(angle)
    backward, angle2, second2 = best(angle.T)
    rows = np.arange(len(angle))
    keep = (angle1 < max_descriptor_distance) & (angle1 < max_ratio * second1) & (backward[forward] == rows)
    keep &= (angle2[forward] < max_ratio * second2[forward])
    return np.stack([rows[keep], forward[keep]], axis=1).astype(np.uint32)
