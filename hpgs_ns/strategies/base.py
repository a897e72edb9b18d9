"""What a trainer strategy is: a config dataclass (`StrategyConfig`, an `InstantiateConfig` with `_target`) and an
object with the hooks below, all no-ops by default, as gsplat's densification strategies have `step_pre_backward`
and `step_post_backward`. The model (`HpgsSplatfactoModel`) builds the active ones from `registry` and calls:

- `at_start(model, start)`: once the pipeline has set the run up (`RunStart`: the start as resolved, the training
  split's cameras); returns what a resumed run must keep of it as text (None: nothing; by default its config's
  `describe()`), and says at start what it will do, or that it does nothing;
- `after_views_added(model, views)`: at the start of training and after each selection round (once the round's
  own follow-up, e.g. `seed-points active`'s triangulation, is done), with the datamanager's `ActiveViews`;
- `loss(model, outputs, batch, step)`: extra loss terms, merged into `get_loss_dict` (nerfstudio sums them);
- `pre_backward(model, step)`: at the end of `get_loss_dict`, just before the trainer's backward;
- `post_backward(model, step)`: in `step_post_backward`, after the optimizers' step and gsplat's densification of
  that step (`model.is_refine_step()` says whether it ran);
- `state()` / `load_state(state)`: what a checkpoint keeps of it (plain numbers); `final_eval()`: what
  `--final-eval-json` records of it.

`step` is the trainer's step (it keeps counting through restarts). A strategy that needs the rendered expected depth
during training says so with `render_depth = True`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Type

import torch
from nerfstudio.configs.base_config import InstantiateConfig


@dataclass
class TrackedPoints:
    """Sparse 3D points and which training views observe each.

    xyz: [P, 3] in the dataparser's world frame (the frame of `cameras.camera_to_worlds`, as splatfacto's seed
        points are).
    observers: [P, V] bool over the training split's V views: observers[p, v] means view v is in point p's track.
    """

    xyz: torch.Tensor
    observers: torch.Tensor
    source: str = ""
    """Where they come from, for the start-up line (e.g. "COLMAP tracks", "the active views' triangulation")."""


@dataclass
class ActiveViews:
    """What strategies see of the datamanager when views are added: the active training views (indices into the
    training split) and the sparse points those views see (None: the run has none, with `why`)."""

    active: List[int]
    points: Optional[TrackedPoints] = None
    why: str = ""
    """Why `points` is None (one clause, for a start-up line)."""


@dataclass
class RenderedView:
    """The camera of the last training render, at the size it was rendered: index into the training split,
    viewmat [4, 4] (OpenCV world-to-camera, as gsplat takes), K [3, 3], width, height."""

    index: int
    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int


@dataclass
class RunStart:
    """What strategies see of the run once the pipeline has set it up."""

    seed_points: str
    """The start as resolved (`colmap`, `colmap-initial`, `active` or `random`; `auto` is one of these by now)."""
    split_cameras: Any
    """The training split's cameras (nerfstudio `Cameras`, active and candidate: poses and intrinsics only)."""
    active_cameras: Callable[[], Any]
    """The active training views' cameras now."""
    training: bool
    """A training run (False: `ns-eval`, `ns-viewer` opening one)."""


class Strategy:
    """The hooks, all no-ops (see the module docstring)."""

    render_depth: bool = False

    def at_start(self, model: Any, start: RunStart) -> Optional[str]:
        config = getattr(self, "config", None)  # what its options say a resumed run must keep
        return config.describe() if isinstance(config, StrategyConfig) else None

    def after_views_added(self, model: Any, views: ActiveViews) -> None:
        return None

    def loss(self, model: Any, outputs: Dict[str, Any], batch: Dict[str, Any], step: int) -> Dict[str, torch.Tensor]:
        return {}

    def pre_backward(self, model: Any, step: int) -> None:
        return None

    def post_backward(self, model: Any, step: int) -> None:
        return None

    def state(self) -> Dict[str, Any]:
        return {}

    def load_state(self, state: Dict[str, Any]) -> None:
        return None

    def final_eval(self) -> Dict[str, Any]:
        return {}


@dataclass
class StrategyConfig(InstantiateConfig):
    """A strategy's options; `setup()` builds the strategy. `active()` False: the model does not build it (nothing
    is computed); `describe()` is what a resumed run must keep (None while off: checkpoints stay as they were)."""

    _target: Type = field(default_factory=lambda: Strategy)

    def active(self) -> bool:
        return True

    def describe(self) -> Optional[str]:
        return None
