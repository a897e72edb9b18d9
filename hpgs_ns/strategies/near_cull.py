"""The floater guard: Gaussians close in front of cameras no training view looks through, removed as densification runs.

gsplat's screen-size prune (splatfacto's `cull-screen-size`) measures a Gaussian's footprint in the view it is
training on; one floating just in front of a camera that never trains (a candidate, or a test view beside one) is
invisible to it, and darkens the test views there. At each densification step this strategy looks from every camera
of the training split (candidates included, their poses only, never their photos) and removes the Gaussians nearer
than `depth` x that camera's median depth and wider than `screen` of its larger image side
(`render.footprints.near_and_large`), unless at least `support` active training views render them on their surface
(`render.footprints.surface_support`: a wall beside a candidate camera, which the training views see, stays).

Unset (`screen` None), it is on (`ACTIVE_START_SCREEN`) where the splat starts from the active views' points
(`seed-points active`, or `auto` on a capture without a point cloud), where those floaters grow, and off from a
capture's points, where it was not judged.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Dict, Optional, Type

import torch
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns.errors import check_option
from hpgs_ns.render.footprints import PinholeViews, near_and_large, surface_support
from hpgs_ns.render.front import training_surfaces
from hpgs_ns.strategies.base import RunStart, Strategy, StrategyConfig

ACTIVE_START_SCREEN = 0.15
"""`screen` where it is left unset and the splat starts from the active views' points (judged for that start only,
with `support` 2)."""

FLAG = "--pipeline.model.near-cull."


@dataclass
class NearCullConfig(StrategyConfig):
    """The floater guard (see `hpgs_ns.strategies.near_cull`)."""

    _target: Type = field(default_factory=lambda: NearCull)
    screen: Optional[float] = None
    """At each densification step, remove the Gaussians that, seen from any camera of the training split (candidates
    included, poses only), lie nearer than `depth` x its median depth and are wider than this fraction of its larger
    image side, unless active training views render them on their surface. None (the default): 0.15 for a splat that
    starts from the active views' points (`seed-points active`, or `auto` on a capture without a point cloud), off
    for the other starts; 0: off for every start."""
    depth: float = 0.25
    """The depth bound, a fraction of each camera's median depth of the Gaussians in its image (no scene unit)."""
    support: int = 2
    """How many active training views must render a suspect on their surface for it to stay. 2: a suspect only one
    view renders there goes too (a real surface is rendered by every view that sees it, a Gaussian reproducing one
    view's pixels from the wrong depth by that view alone); 1: one is enough."""

    def __post_init__(self) -> None:
        check_option(FLAG + "screen", self.screen, self.screen is None or 0 <= self.screen < 1,
                     "must be at least 0 and below 1 (a fraction of the image's larger side)", "0 turns it off")
        check_option(FLAG + "depth", self.depth, 0 < self.depth <= 1,
                     "must be above 0 and at most 1 (a fraction of each camera's median depth)")
        check_option(FLAG + "support", self.support, self.support >= 1,
                     "must be at least 1 (training views)", "pass 1 (one view is enough) or 2")

    def screen_for(self, seed_points: str) -> float:
        """`screen` as a run with start `seed_points` uses it."""
        if self.screen is not None:
            return float(self.screen)
        return ACTIVE_START_SCREEN if seed_points == "active" else 0.0


def signature(screen: float, depth: float, support: int) -> str:
    """The resume signature's "near-cull" text (support 1, the first version's rule, as its checkpoints carry it)."""
    return f"{screen:g} {depth:g}" + (f" support {support}" if support != 1 else "")


class NearCull(Strategy):
    """Removes near, wide Gaussians no training surface holds, at densification's steps (see the module docstring)."""

    def __init__(self, config: NearCullConfig) -> None:
        self.config = config
        self.screen = 0.0
        """`screen` as this run uses it (set at start from the option and the start); 0: off."""
        self.views: Optional[PinholeViews] = None
        """The cameras it looks from: the training split's, active and candidate."""
        self.active_cameras = None
        """The active training views' cameras now: where it checks surfaces."""
        self.culled = 0
        """How many Gaussians it has removed in this run so far."""

    def at_start(self, model: Any, start: RunStart) -> Optional[str]:
        cfg = self.config
        self.screen = cfg.screen_for(start.seed_points)
        if self.screen <= 0:
            if start.training:
                defaults = {f.name: f.default for f in fields(NearCullConfig)}
                idle = [FLAG + name for name in ("depth", "support") if getattr(cfg, name) != defaults[name]]
                if idle:
                    off = "0 (off)" if cfg.screen is not None else "off by default for this start"
                    CONSOLE.print(f"[yellow]{' and '.join(idle)} {'does' if len(idle) == 1 else 'do'} nothing in this run: "
                                  f"{FLAG}screen is {off}; pass {FLAG}screen 0.15 to turn the cull on", soft_wrap=True)
            return None
        if start.training:
            self.views = PinholeViews.from_cameras(start.split_cameras, model.device)
            self.active_cameras = start.active_cameras
            by_start = " (the active start's default)" if cfg.screen is None else ""
            holds = ("a training view shows them on its surface" if cfg.support == 1 else
                     f"{cfg.support} training views show them on their surfaces")
            CONSOLE.print(f"near-cull screen {self.screen:g}{by_start}: at each densification step, Gaussians nearer than "
                          f"{cfg.depth:g} x the median depth of any of the {len(self.views)} training-split cameras (poses "
                          f"only) and wider than {self.screen:g} of its image are removed unless {holds}", soft_wrap=True)
        return signature(self.screen, float(cfg.depth), int(cfg.support))

    def post_backward(self, model: Any, step: int) -> None:
        if self.screen > 0 and model.is_refine_step():
            self.cull(model, step)

    @torch.no_grad()
    def cull(self, model: Any, step: Optional[int] = None) -> int:
        """Remove, now, the Gaussians `near_and_large` finds from `views` that fewer than `support` active training
        views show on their rendered surface; gsplat's `remove` keeps the optimizers' and the densification state's
        rows in step. Never the whole splat. Returns how many."""
        from gsplat.strategy.ops import remove  # pure PyTorch: safe on a CPU machine

        if self.views is None or model.num_points == 0:
            return 0
        means = model.means.detach()
        mask = near_and_large(means, torch.exp(model.scales.detach()), self.views, self.screen, self.config.depth)
        if bool(mask.any()) and self.active_cameras is not None:
            views, depths, alphas = training_surfaces(model, self.active_cameras())
            picked = mask.nonzero().squeeze(1)
            mask[picked] = surface_support(means[picked], views, depths, alphas) < self.config.support
        count = int(mask.sum())
        if count == 0 or count >= model.num_points:
            return 0
        remove(params=model.gauss_params, optimizers=model.optimizers, state=model.strategy_state, mask=mask)
        self.culled += count
        from nerfstudio.utils import writer

        writer.put_scalar("train/near_culled", count, model.step + model.step_offset if step is None else step)
        return count

    def state(self) -> Dict[str, Any]:
        return {"culled": int(self.culled)}

    def load_state(self, state: Dict[str, Any]) -> None:
        self.culled = int(state.get("culled", 0))

    def final_eval(self) -> Dict[str, Any]:
        return {"near_culled": int(self.culled)} if self.screen > 0 else {}
