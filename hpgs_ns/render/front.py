"""The training views' rendered surfaces, and what lies in front of each test camera (the final eval's account).

The floater guard (`hpgs_ns.strategies.near_cull`) checks its suspects against `training_surfaces`; `describe_front`
reports, for each test camera, the Gaussians in front of it, beside that view's PSNR in `--final-eval-json`.
"""

from __future__ import annotations

import copy
from typing import Any, Dict, List, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras

from hpgs_ns.render.footprints import FRONT_DEPTH, FRONT_SCREEN, PinholeViews, in_front, near_and_large, reach_any_image, surface_support

SURFACE_SHORT_SIDE = 160
"""The short side (pixels) the training views are rendered at to read their surfaces: depth at that size is enough
to say whether a Gaussian sits on one, at a fraction of a full render's cost."""


def small(cameras: Cameras, short_side: int = SURFACE_SHORT_SIDE) -> Cameras:
    """A copy of `cameras` with the short side at most `short_side` (never enlarged)."""
    cameras = copy.deepcopy(cameras)
    short = torch.minimum(cameras.width, cameras.height).float()
    cameras.rescale_output_resolution(torch.clamp(short_side / short, max=1.0))
    return cameras


@torch.no_grad()
def training_surfaces(model, cameras: Cameras, short_side: int = SURFACE_SHORT_SIDE
                      ) -> Tuple[PinholeViews, List[torch.Tensor], List[torch.Tensor]]:
    """`cameras` rendered by `model` (eval mode, short side at most `short_side`): their cameras at that size,
    expected depths and opacities ([H, W] each)."""
    cameras = small(cameras, short_side)
    depths, alphas = [], []
    for k in range(cameras.shape[0]):
        _, render, alpha = model._eval_render(cameras[k : k + 1], "RGB+ED")
        depths.append(render[0, ..., 3])
        alphas.append(alpha[0, ..., 0])
    return PinholeViews.from_cameras(cameras, model.means.device), depths, alphas


@torch.no_grad()
def cover(model, camera: Cameras, gaussians: torch.Tensor, short_side: int = SURFACE_SHORT_SIDE) -> float:
    """The mean opacity the Gaussians `gaussians` ([N] bool) alone render over `camera`'s ([1]) image, rendered at
    `short_side` px on its short side."""
    camera = small(camera, short_side).to(model.device)
    with model.eval_mode():
        _, alpha, _ = model._rasterize_cameras(camera.camera_to_worlds.reshape(-1, 3, 4),
                                               camera.get_intrinsics_matrices().reshape(-1, 3, 3),
                                               int(camera.width[0].item()), int(camera.height[0].item()),
                                               crop_ids=gaussians.to(model.device))
    return float(alpha.mean())


@torch.no_grad()
def describe_front(model, cameras: Cameras, training: Cameras, split: Optional[Cameras] = None) -> List[Dict[str, Any]]:
    """For each camera of `cameras` (the test views), what lies in front of it (`render.footprints.in_front`):
    `front_gaussians`, `front_cover` (the mean opacity they alone render over its image: the haze they lay on it),
    `front_large` (of those, wide in its image), the large ones' median and largest sigma (largest axis, the
    splat's units: what a 3D-scale prune compares), the shares of them that one, and two or more, views of
    `training` render on their surface (`surface_support`), that reach into a `training` view's image
    (`front_large_in_view`: a view that can pull on them) and, given `split` (the training split's cameras,
    candidates included), that the floater guard's test flags from one of those cameras at its default bounds
    (`front_large_suspect`); {} for an empty splat."""
    if model.num_points == 0:
        return [{} for _ in range(cameras.shape[0])]
    device = model.means.device
    views = PinholeViews.from_cameras(cameras, device)
    means, scales = model.means.detach(), torch.exp(model.scales.detach())
    out: List[Dict[str, Any]] = []
    surfaces = seen = suspects = None
    for k in range(len(views)):
        front, large = in_front(means, scales, views, k)
        entry: Dict[str, Any] = {"front_gaussians": int(front.sum()), "front_large": int(large.sum()),
                                 "front_cover": cover(model, cameras[k : k + 1], front) if bool(front.any()) else 0.0}
        if entry["front_large"]:
            sigma = scales[large].max(dim=-1).values
            if surfaces is None:
                surfaces = training_surfaces(model, training)
            support = surface_support(means[large], *surfaces)
            if seen is None:  # computed once, for every Gaussian: the guard's depth bound is each camera's median
                seen = reach_any_image(means, scales, PinholeViews.from_cameras(training, device))
                if split is not None:
                    suspects = near_and_large(means, scales, PinholeViews.from_cameras(split, device),
                                              FRONT_SCREEN, FRONT_DEPTH)
            entry.update(front_large_sigma_median=float(sigma.median()), front_large_sigma_max=float(sigma.max()),
                         front_large_on_surface=float((support >= 1).float().mean()),
                         front_large_on_two_surfaces=float((support >= 2).float().mean()),
                         front_large_in_view=float(seen[large].float().mean()))
            if suspects is not None:
                entry["front_large_suspect"] = float(suspects[large].float().mean())
        out.append(entry)
    return out
