"""Seed points where a new view's render is wrong (`--pipeline.selection.after-add.error-points`).

A view added late shows content the splat lacks. Without this, that content enters as the points the round's
triangulation finds away from the splat (`seed-points active`: a few hundred) or not at all, and must then grow
from neighbouring Gaussians in the steps left. Here the view's own pixels seed it: pixels drawn where the splat's
render of the view is furthest from the photo, each a Gaussian on its pixel's ray, in the photo's colour, at the
render's depth where the render is opaque (a surface is there, in the wrong colour) and at a drawn distance where
it is not (as `random-points views` draws them: `hpgs_ns.scenes.view_points`). gsplat's strategies only split,
clone and prune Gaussians that exist, and nerfstudio seeds from point clouds, so this is written here.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from hpgs_ns.render.viewmats import world_to_camera
from hpgs_ns.scenes.view_points import FAR, NEAR

OPAQUE = 0.5
"""A pixel whose render is at least this opaque has a surface at its expected depth; below it, the depth is drawn.
A design rule (half the light stops there), not tuned."""


def pixel_errors(render: torch.Tensor, photo: torch.Tensor) -> torch.Tensor:
    """[H, W] mean absolute colour difference of a render and its photo ([H, W, 3] each, in [0, 1])."""
    return (render.float() - photo.float()).abs().mean(-1)


def error_weights(errors: torch.Tensor) -> torch.Tensor:
    """[H, W] how likely each pixel is drawn: its error where it exceeds the view's median error, else 0. The median
    cut keeps the draws off the small error a fitted splat leaves everywhere (a design rule, not tuned). Where no
    pixel exceeds it (half the view or more equally wrong, as an empty render of a plain wall), every pixel's
    error."""
    above = torch.where(errors > errors.median(), errors, torch.zeros_like(errors))
    return above if bool((above > 0).any()) else errors


def points_where_render_errs(
    K: torch.Tensor,
    camera_to_world: torch.Tensor,
    render: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    photo: torch.Tensor,
    count: int,
    distance: float,
    generator: Optional[torch.Generator] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Up to `count` points on the rays of the pixels a render gets most wrong, drawn without replacement in
    proportion to `error_weights`, for one pinhole camera (K [3, 3]; camera_to_world [3, 4], nerfstudio's OpenGL
    pose): at the render's z-depth `depth` [H, W, 1] where `alpha` [H, W, 1] >= OPAQUE, else at a z-depth drawn in
    [NEAR, FAR] x `distance` (uniform in 1 / depth), coloured by `photo` [H, W, 3] in [0, 1]. `render` [H, W, 3].
    Returns (xyz float [n, 3], rgb uint8 [n, 3]); n < count when fewer pixels have weight."""
    render, depth, alpha, photo = (t.detach().float().cpu() for t in (render, depth, alpha, photo))
    if render.shape[:2] != photo.shape[:2]:
        raise ValueError(f"error points: a {tuple(render.shape[:2])} render of a {tuple(photo.shape[:2])} photo")
    height, width = photo.shape[:2]
    weights = error_weights(pixel_errors(render, photo)).flatten().double()
    n = min(int(count), int((weights > 0).sum()))
    if n < 1:
        return torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.uint8)
    pixel = torch.multinomial(weights, n, replacement=False, generator=generator)
    y, x = pixel // width, pixel % width
    u = torch.rand(n, generator=generator)
    drawn = float(distance) / (1 / FAR + u * (1 / NEAR - 1 / FAR))
    z = torch.where(alpha[y, x, 0] >= OPAQUE, depth[y, x, 0], drawn)
    K = K.detach().float().cpu()
    # OpenCV camera space (x right, y down, z forward), as the rasterizer projects
    camera_points = torch.stack([(x + 0.5 - K[0, 2]) / K[0, 0] * z, (y + 0.5 - K[1, 2]) / K[1, 1] * z, z], dim=-1)
    to_world = torch.linalg.inv(world_to_camera(camera_to_world.detach().float().cpu()[None, :3, :4])[0])
    xyz = camera_points @ to_world[:3, :3].T + to_world[:3, 3]
    rgb = (photo[y, x, :3].clamp(0, 1) * 255).round().to(torch.uint8)
    return xyz, rgb
