"""World-to-camera matrices (gsplat's convention) from nerfstudio camera-to-world poses.

Same maths as nerfstudio's `splatfacto.get_viewmat`, without its `torch.compile`: that one recompiles for every
new batch shape and device, which made the first Fisher round on an H100 take ~70 s instead of ~5 s (inductor
C++ builds for CPU-side camera batches of 32, 20 and 7 views).
"""

from __future__ import annotations

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
