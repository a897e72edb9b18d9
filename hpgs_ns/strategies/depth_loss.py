"""The depth loss of HP-GS: the rendered depth supervised in disparity space at the sparse points the views see.

HP-GS (its section 2) trains splatfacto with "a depth loss in disparity space" beside L1 + SSIM, from a monocular
depth model. None can be loaded here, so the depth it supervises is the sparse points' own: for the training view v
of a step, each point p whose track contains v is projected into v, and the term is

    weight * mean_p | 1 / D_v(u_p) - 1 / z_p |

where z_p is p's depth in v's camera, u_p its pixel (the pixel it falls in, at the render's size) and D_v the
rendered expected depth there. Points behind the camera (z below `MIN_DEPTH`), outside the image or where the
render is empty (alpha 0) are left out; a view with none adds 0. The points (`ActiveViews.points`, the
datamanager's) are the COLMAP model's with their tracks cut to the active views, or the `active` start's
triangulation of the active views, rebuilt whenever views are added: a point that only withheld or test views see
never supervises anything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Type

import torch

from hpgs_ns.errors import check_option
from hpgs_ns.strategies.base import ActiveViews, Strategy, StrategyConfig

MIN_DEPTH = 1e-3
"""Points (and rendered depths) nearer than this, in the scene's units, are left out: their disparity is unbounded."""


def project(xyz: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor):
    """Points xyz [P, 3] in camera `viewmat` [4, 4] (OpenCV world-to-camera) with intrinsics K [3, 3]: (pixel
    coordinates [P, 2], z-depth [P])."""
    cam = xyz @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    safe = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
    uv = (cam[:, :2] / safe[:, None]) @ K[:2, :2].T + K[:2, 2]
    return uv, z


def disparity_residuals(xyz: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, depth: torch.Tensor,
                        alpha: Optional[torch.Tensor] = None) -> torch.Tensor:
    """|1 / depth(u_p) - 1 / z_p| [M] for the points of xyz [P, 3] that lie in front of the camera and inside the
    image of depth [H, W] or [H, W, 1] (the rendered expected z-depth; alpha [H, W(, 1)]: only where it is > 0).
    Differentiable in `depth`; never NaN."""
    depth = depth.reshape(depth.shape[0], depth.shape[1])
    height, width = depth.shape
    xyz = xyz.to(device=depth.device, dtype=depth.dtype)
    uv, z = project(xyz, viewmat.to(xyz), K.to(xyz))
    col, row = torch.floor(uv[:, 0]), torch.floor(uv[:, 1])  # the pixel a point falls in (centres at +0.5)
    keep = (z > MIN_DEPTH) & (col >= 0) & (col < width) & (row >= 0) & (row < height) & torch.isfinite(uv).all(-1)
    col, row, z = col[keep].long(), row[keep].long(), z[keep]
    rendered = depth[row, col]
    valid = torch.isfinite(rendered) & (rendered.detach() > MIN_DEPTH)
    if alpha is not None:
        valid &= alpha.reshape(height, width)[row, col] > 0
    return (1.0 / rendered[valid] - 1.0 / z[valid]).abs()


@dataclass
class DepthLossConfig(StrategyConfig):
    """HP-GS's "depth loss in disparity space" (Sec. 2), on the sparse points the active views see instead of a
    monocular depth model: weight x the mean |1/rendered depth - 1/point depth| at the points of the step's view
    (`hpgs_ns.strategies.depth_loss`). Off by default (weight 0)."""

    _target: Type = field(default_factory=lambda: DepthLoss)
    weight: float = 0.0
    """The depth term's weight beside splatfacto's L1 + SSIM (0: off, nothing computed)."""
    start_step: int = 0
    """The first trainer step it acts at (before: no term)."""

    def __post_init__(self) -> None:
        flag = "--pipeline.model.depth-loss."
        check_option(flag + "weight", self.weight, math.isfinite(self.weight) and self.weight >= 0,
                     "must be a finite weight >= 0", "pass 0 (off) or e.g. 0.05")
        check_option(flag + "start-step", self.start_step, self.start_step >= 0, "must be >= 0",
                     "pass 0 to act from the first step")

    def active(self) -> bool:
        return self.weight > 0

    def describe(self) -> Optional[str]:
        return f"{self.weight:g} from {self.start_step}" if self.active() else None


class DepthLoss(Strategy):
    """The depth loss (see the module docstring): its points are set by `after_views_added`."""

    render_depth = True

    def __init__(self, config: DepthLossConfig) -> None:
        self.config = config
        self.xyz: Optional[torch.Tensor] = None
        """[P, 3] the points some active view sees (None: none yet)."""
        self.observers: Optional[torch.Tensor] = None
        """[P, V] bool: the active views in each point's track."""
        self.told = False

    def after_views_added(self, model: Any, views: ActiveViews) -> None:
        from nerfstudio.utils.rich_utils import CONSOLE

        points = views.points
        if points is None or points.xyz.shape[0] == 0:
            self.xyz = self.observers = None
            if not self.told:
                CONSOLE.print(f"[yellow]--pipeline.model.depth-loss.weight {self.config.weight:g} does nothing in this "
                              f"run: {views.why or 'the active views see no sparse points'}", soft_wrap=True)
            self.told = True
            return
        observers = torch.zeros_like(points.observers, dtype=torch.bool)
        active = torch.tensor(sorted(views.active), dtype=torch.long)
        observers[:, active] = points.observers[:, active].bool()  # never a withheld or test view's observation
        seen = observers.any(1)
        self.xyz, self.observers = points.xyz[seen].float().cpu(), observers[seen].cpu()
        if not self.told:
            CONSOLE.print(f"depth loss {self.config.weight:g}: disparity at the {int(seen.sum())} points of "
                          f"{points.source or 'the sparse points'} that the {len(views.active)} active views see "
                          "(rebuilt after each round)", soft_wrap=True, highlight=False)
        self.told = True

    def loss(self, model: Any, outputs: Dict[str, Any], batch: Dict[str, Any], step: int) -> Dict[str, torch.Tensor]:
        view = getattr(model, "last_view", None)
        depth = outputs.get("depth")
        if step < self.config.start_step or self.xyz is None or view is None or depth is None:
            return {}
        if not 0 <= view.index < self.observers.shape[1]:
            return {}
        mine = self.observers[:, view.index]
        residuals = disparity_residuals(self.xyz[mine], view.viewmat, view.K, depth, outputs.get("accumulation"))
        if residuals.numel() == 0:
            return {"depth_loss": depth.sum() * 0.0}
        return {"depth_loss": self.config.weight * residuals.mean()}
