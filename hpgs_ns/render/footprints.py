"""Which Gaussians sit close in front of a camera and fill much of its image (the floater guard, `--pipeline.model.near-cull.*`,
and the final eval's account of what lies in front of each test camera).

gsplat's screen-size prune (splatfacto's `cull-screen-size`) measures a Gaussian's footprint in the view it is
training on; a Gaussian floating just in front of a camera that never trains (a candidate view, or a test view
beside one) is invisible to it. This measures the footprint in any cameras, from their poses alone, by projecting
the Gaussians' centres: no rasterization (gsplat has no projection-only call that runs on CPU), so the footprint is
gsplat's 3-sigma radius bounded by the largest axis, which is what a prune needs (it never underestimates).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import torch

from hpgs_ns.render.viewmats import world_to_camera

NEAR_PLANE = 0.01
"""gsplat's default near plane: Gaussians nearer than this are not drawn."""


@dataclass(frozen=True)
class PinholeViews:
    """Cameras by pose and intrinsics only (no photos): world-to-camera [C, 4, 4] (OpenCV), fx, fy, cx, cy,
    width, height [C]."""

    viewmats: torch.Tensor
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor

    @classmethod
    def from_cameras(cls, cameras, device=None) -> PinholeViews:
        """From nerfstudio `Cameras` [C] (OpenGL camera-to-world poses)."""
        def flat(t: torch.Tensor) -> torch.Tensor:
            return t.reshape(-1).float().to(device)

        return cls(world_to_camera(cameras.camera_to_worlds.float()).to(device), flat(cameras.fx), flat(cameras.fy),
                   flat(cameras.cx), flat(cameras.cy), flat(cameras.width), flat(cameras.height))

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    def pixels(self, means: torch.Tensor, cameras: slice) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Centres `means` [N, 3] in these `cameras`: (z, u, v), each [C, N]: depth along each view and pixel
        position (u, v computed with z clamped to the near plane)."""
        vm = self.viewmats[cameras].to(means.device)
        fx, fy, cx, cy = (t[cameras].to(means.device)[:, None] for t in (self.fx, self.fy, self.cx, self.cy))
        p = torch.einsum("cij,nj->cni", vm[:, :3, :3], means) + vm[:, None, :3, 3]
        z = p[..., 2]
        zc = z.clamp(min=NEAR_PLANE)
        return z, fx * p[..., 0] / zc + cx, fy * p[..., 1] / zc + cy


@torch.no_grad()
def near_and_large(means: torch.Tensor, scales: torch.Tensor, views: PinholeViews, screen: float, depth: float,
                   chunk: int = 8) -> torch.Tensor:
    """[N] bool: the Gaussians (centres `means` [N, 3], world-space standard deviations `scales` [N, 3]) that, in at
    least one of `views`, lie in front of the camera nearer than `depth` x the median depth of the centres that
    project into its image (the camera's own scale, so no scene unit enters) and whose footprint reaches into the
    image with a radius above `screen` x its larger side (gsplat's screen-size measure)."""
    flagged = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    if means.shape[0] == 0 or len(views) == 0:
        return flagged
    for start in range(0, len(views), chunk):
        z, inside, reaches, large = footprints(means, scales, views, slice(start, start + chunk), screen)
        typical = torch.where(inside, z, torch.full_like(z, float("nan"))).nanmedian(dim=1).values  # [C]
        near = z < depth * typical[:, None]  # NaN (nothing in the image) compares False
        flagged |= (reaches & near & large).any(dim=0)
    return flagged


def footprints(means: torch.Tensor, scales: torch.Tensor, views: PinholeViews, cameras: slice,
               screen: float) -> Tuple[torch.Tensor, ...]:
    """Each Gaussian in each of `views[cameras]`, [C, N] each: its centre's depth; whether the centre falls in the
    image; whether its footprint (gsplat's 3-sigma radius of the largest axis) reaches into it; whether that radius
    is above `screen` x the image's larger side."""
    radius_world = 3.0 * scales.max(dim=-1).values
    fx, fy, w, h = (t[cameras].to(means.device)[:, None] for t in (views.fx, views.fy, views.width, views.height))
    z, u, v = views.pixels(means, cameras)
    front = z > NEAR_PLANE
    r = torch.maximum(fx, fy) * radius_world[None, :] / z.clamp(min=NEAR_PLANE)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    reaches = front & (u > -r) & (u < w + r) & (v > -r) & (v < h + r)
    return z, inside, reaches, r > screen * torch.maximum(w, h)


FRONT_DEPTH = 0.25
"""`in_front`'s depth bound: a fraction of the median depth of the centres in the view's image (the floater guard's `depth`
default)."""
FRONT_SCREEN = 0.15
"""`in_front`'s "large": a footprint radius above this fraction of the image's larger side (cull-screen-size's)."""


@torch.no_grad()
def in_front(means: torch.Tensor, scales: torch.Tensor, views: PinholeViews, k: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """[N] bool masks for view `k`: the Gaussians whose footprint reaches its image from nearer than FRONT_DEPTH x
    the median depth of the centres in it (as `near_and_large`: a haze over the image does not move that median,
    while it moves the render's), and of those the ones wider than FRONT_SCREEN of the image: what lies between
    the camera and what it shows."""
    z, inside, reaches, large = (t[0] for t in footprints(means, scales, views, slice(k, k + 1), FRONT_SCREEN))
    if not bool(inside.any()):
        none = torch.zeros_like(reaches)
        return none, none
    front = reaches & (z < FRONT_DEPTH * z[inside].median())
    return front, front & large


@torch.no_grad()
def reach_any_image(means: torch.Tensor, scales: torch.Tensor, views: PinholeViews, chunk: int = 8) -> torch.Tensor:
    """[N] bool: the Gaussians whose footprint (as `footprints` measures it) reaches into at least one of `views`'
    images from in front of the camera: those a render of one of them can pull on."""
    reached = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    for start in range(0, len(views), chunk):
        reached |= footprints(means, scales, views, slice(start, start + chunk), 1.0)[2].any(dim=0)
    return reached


SURFACE_TOLERANCE = 0.2
"""How much nearer than a view's rendered surface (as a fraction of its depth) a centre must lie to be off it: the
expected depth blends surfaces at edges, so a centre within this of it counts as on the surface."""


@torch.no_grad()
def surface_support(means: torch.Tensor, views: PinholeViews, depths, alphas) -> torch.Tensor:
    """[N] int: how many views of `views` show each centre `means` [N, 3] on their rendered surface (`depths[k]`,
    `alphas[k]`: view k's expected depth and opacity, [H, W] at that view's size). A centre is on view k's surface
    where it falls in k's image, over a pixel at least half opaque, within SURFACE_TOLERANCE of that pixel's depth
    (in front of it: k sees through it; behind it: k cannot see it). A real surface is rendered there by every view
    that sees it; a Gaussian that reproduces one view's pixels from the wrong depth, by that view alone."""
    count = torch.zeros(means.shape[0], dtype=torch.long, device=means.device)
    for k in range(len(views)):
        z, u, v = (t[0] for t in views.pixels(means, slice(k, k + 1)))
        front = z > NEAR_PLANE
        u, v = u.floor().long(), v.floor().long()
        depth, alpha = depths[k].to(means.device), alphas[k].to(means.device)
        inside = front & (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
        ui, vi = u.clamp(0, depth.shape[1] - 1), v.clamp(0, depth.shape[0] - 1)
        surface, opaque = depth[vi, ui], alpha[vi, ui] >= 0.5
        count += inside & opaque & ((z - surface).abs() <= SURFACE_TOLERANCE * surface)
    return count
