"""world_to_camera: the inverse of the OpenGL->OpenCV-flipped camera-to-world pose, for any batch size."""

import torch

from hpgs_ns.render.viewmats import world_to_camera


def random_poses(n: int, generator: torch.Generator) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=generator, dtype=torch.float64))
    q = q * torch.sign(torch.linalg.det(q))[:, None, None]  # proper rotations
    t = torch.randn(n, 3, 1, generator=generator, dtype=torch.float64)
    return torch.cat([q, t], dim=2)


def test_world_to_camera_inverts_flipped_pose():
    g = torch.Generator().manual_seed(0)
    for n in (1, 7, 32):
        c2w = random_poses(n, g)
        full = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
        full[:, :3, :4] = c2w
        flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
        expected = torch.linalg.inv(full @ flip)
        torch.testing.assert_close(world_to_camera(c2w), expected, rtol=0, atol=1e-12)


def test_camera_centre_maps_to_origin_and_forward_is_plus_z():
    c2w = random_poses(5, torch.Generator().manual_seed(1))
    centres = torch.cat([c2w[:, :, 3], torch.ones(5, 1, dtype=torch.float64)], dim=1)
    vm = world_to_camera(c2w)
    torch.testing.assert_close((vm @ centres[:, :, None])[:, :3, 0], torch.zeros(5, 3, dtype=torch.float64), rtol=0, atol=1e-12)
    # OpenGL looks down -z: a point one unit ahead of the camera has OpenCV depth +1.
    ahead = c2w[:, :, 3] - c2w[:, :, 2]
    p = vm @ torch.cat([ahead, torch.ones(5, 1, dtype=torch.float64)], dim=1)[:, :, None]
    torch.testing.assert_close(p[:, 2, 0], torch.ones(5, dtype=torch.float64), rtol=0, atol=1e-12)
