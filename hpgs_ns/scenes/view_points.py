"""Seed points along the active views' pixel rays, for a splat that has no points to start from
(`--pipeline.datamanager.random-points views`).

splatfacto's random start fills a cube of side `--pipeline.model.random-scale` (10) around the origin. In
nerfstudio's normalised frame, where the cameras fit in [-1, 1], that puts 0.0-0.1% of the points where the
object captures' COLMAP points are (`benchmarks/random_start_coverage.py`). Here every point lies on a ray of an
active view, at a distance around where the views' optical axes meet, and takes its pixel's colour: it is in front
of a view, and the view sees it in about the right colour from step 0. No maintained library does this
(gsplat's trainers and splatfacto sample a cube), so it is written here.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras

NEAR, FAR = 0.5, 3.0
"""Distances along a ray, as multiples of the view's distance to where the optical axes meet: from half-way
there (an object's near side) to three times as far (a room's walls behind it). Sampled uniformly in 1 / distance,
as NeRF samples unbounded scenes: denser near the object than in the background. A design rule, not tuned."""


def axes_meeting_point(centres: torch.Tensor, forwards: torch.Tensor) -> Optional[torch.Tensor]:
    """The point nearest (least squares) to every camera's optical axis, or None when the axes are (nearly)
    parallel or the point is behind the cameras (a forward-facing capture)."""
    eye = torch.eye(3, dtype=torch.float64)
    f = torch.nn.functional.normalize(forwards.double(), dim=-1)
    projector = eye - f[:, :, None] * f[:, None, :]  # [V, 3, 3]: removes the component along each axis
    a = projector.sum(0)
    b = (projector @ centres.double()[:, :, None]).sum(0)[:, 0]
    eigenvalues = torch.linalg.eigvalsh(a)
    if eigenvalues[0] < 1e-3 * eigenvalues[-1]:
        return None
    point = torch.linalg.solve(a, b)
    if ((point - centres.double()) * f).sum(-1).median() <= 0:
        return None
    return point.float()


def view_distances(cameras: Cameras, views: Sequence[int]) -> torch.Tensor:
    """Each view's distance along its optical axis to where the views' axes meet; the cameras' spread (median
    distance of a centre to their mean) where they do not meet."""
    c2w = cameras.camera_to_worlds[torch.as_tensor(list(views))]
    centres, forwards = c2w[:, :3, 3], -c2w[:, :3, 2]  # nerfstudio cameras look along -z
    point = axes_meeting_point(centres, forwards) if len(views) >= 2 else None
    if point is not None:
        distance = ((point - centres) * torch.nn.functional.normalize(forwards, dim=-1)).sum(-1)
        fallback = distance[distance > 0].median()
        return torch.where(distance > 0, distance, fallback)
    all_centres = cameras.camera_to_worlds[:, :3, 3]
    spread = (all_centres - all_centres.mean(0)).norm(dim=-1).median().clamp(min=1e-3)
    return spread.expand(len(views)).clone()


def points_along_views(cameras: Cameras, image: Callable[[int], np.ndarray], views: Sequence[int], count: int,
                       generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """`count` points on random pixel rays of `views` (the same number from each, give or take one), at distances
    drawn in [NEAR, FAR] x the view's distance to where the axes meet (uniform in 1 / distance), coloured by
    their pixel (`image(view)`: uint8 [H, W, C] at the camera's size). Returns (xyz float [count, 3],
    rgb uint8 [count, 3])."""
    views = [int(v) for v in views]
    cameras = cameras.to("cpu")  # the draws are CPU tensors (seeded generator); a restart may find them on the GPU
    if not views or count < 1:
        return torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.uint8)
    distances = view_distances(cameras, views)
    per_view = np.diff(np.linspace(0, count, len(views) + 1).round().astype(int))
    xyz, rgb = [], []
    for k, (view, n) in enumerate(zip(views, per_view)):
        if n == 0:
            continue
        height, width = int(cameras.height[view]), int(cameras.width[view])
        y = torch.randint(0, height, (n,), generator=generator)
        x = torch.randint(0, width, (n,), generator=generator)
        coords = torch.stack([y, x], dim=-1).float() + 0.5  # pixel centres, as nerfstudio's image coords
        rays = cameras.generate_rays(camera_indices=torch.full((n, 1), view, dtype=torch.long), coords=coords)
        u = torch.rand(n, generator=generator)
        inverse = 1 / FAR + u * (1 / NEAR - 1 / FAR)
        along = distances[k] / inverse
        xyz.append(rays.origins + rays.directions * along[:, None])
        pixels = torch.from_numpy(np.asarray(image(view)))
        rgb.append(pixels[y, x, :3])
    return torch.cat(xyz).float(), torch.cat(rgb).to(torch.uint8)
