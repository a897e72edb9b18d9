"""World-to-camera matrices (gsplat's convention) from nerfstudio camera-to-world poses.

Same maths as nerfstudio's `splatfacto.get_viewmat`, without its `torch.compile`: that one recompiles for every
new batch shape and device, which made the first Fisher round on an H100 take ~70 s instead of ~5 s (inductor
C++ builds for CPU-side camera batches of 32, 20 and 7 views).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Iterator, List, Sequence, Tuple, Union

import torch


def world_to_camera(camera_to_world: torch.Tensor) -> torch.Tensor:
    """[B, 3, 4] (or [B, 4, 4]) OpenGL camera-to-world poses -> [B, 4, 4] OpenCV world-to-camera matrices."""
    flip = torch.tensor([1.0, -1.0, -1.0], device=camera_to_world.device, dtype=camera_to_world.dtype)
    R_inv = (camera_to_world[:, :3, :3] * flip).transpose(1, 2)
    viewmat = torch.zeros(camera_to_world.shape[0], 4, 4, device=camera_to_world.device, dtype=camera_to_world.dtype)
    viewmat[:, :3, :3] = R_inv
    viewmat[:, :3, 3:4] = -R_inv @ camera_to_world[:, :3, 3:4]
    viewmat[:, 3, 3] = 1.0
    return viewmat


@dataclass
class ViewBatch:
    """Views of one rendered size, with their cameras in the rasterizer's form."""

    views: List[int]
    viewmats: torch.Tensor
    """[C, 4, 4] world-to-camera."""
    Ks: torch.Tensor
    """[C, 3, 3] intrinsics at the rendered size."""
    width: int
    height: int


def view_batches(cameras, views: Sequence[int], resolution_scale: float, view_batch: int,
                 to: Union[torch.device, torch.Tensor]) -> Iterator[ViewBatch]:
    """`views` (indices into nerfstudio `cameras`) rendered at `resolution_scale`, grouped by rendered size, at most
    `view_batch` per group; matrices moved `.to(to)` (a device, or a tensor whose dtype and device they take)."""
    picked = cameras[torch.tensor([int(v) for v in views], dtype=torch.long)]
    if resolution_scale != 1.0:
        picked.rescale_output_resolution(resolution_scale)
    sizes: Dict[Tuple[int, int], List[int]] = {}
    for k in range(len(views)):
        sizes.setdefault((int(picked.width[k]), int(picked.height[k])), []).append(k)
    for (W, H), rows in sizes.items():
        for start in range(0, len(rows), view_batch):
            chunk = rows[start : start + view_batch]
            cams = picked[torch.tensor(chunk, dtype=torch.long)]
            yield ViewBatch(
                views=[int(views[k]) for k in chunk],
                viewmats=world_to_camera(cams.camera_to_worlds.reshape(-1, 3, 4)).to(to),
                Ks=cams.get_intrinsics_matrices().reshape(-1, 3, 3).to(to),
                width=W,
                height=H,
            )
