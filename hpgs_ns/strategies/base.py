"""What a trainer strategy is: a config dataclass (`StrategyConfig`, an `InstantiateConfig` with `_target`) and an
object with the hooks below, all no-ops by default, as gsplat's densification strategies have `step_pre_backward`
and `step_post_backward`. The model (`HpgsSplatfactoModel`) builds the active ones from `registry` and calls:

- `at_start(model, start)`: once the pipeline has set the run up (`RunStart`: the start as resolved, the training
  split's cameras); returns what a resumed run must keep of it as text, kept under its name (None: nothing; by
  default its config's `describe()`), or as {signature key: text}, and says at start what it will do, or that it
  does nothing;
- `plan(model, plan)`: once training is about to start (a resumed run: once its checkpoint is loaded), with the
  rounds it will run (`RoundsPlan`: the initial views, the views the run will end with);
- `after_round(model, added)`: right after a round's views joined the active set (`RoundAdded`: the step, the view
  counts before and after, the trainer's optimizers); returns what it did as a frozen dataclass with
  `recorded_in(record)`, which the round's record keeps (None: nothing);
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

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Type, Union

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


@dataclass(frozen=True)
class RoundsPlan:
    """What strategies see of the selection rounds as training starts."""

    initial_views: int
    final_views: int
    """The active views the run will end with (what is active now and what the rounds still to run add)."""
    seed_points: str
    """The start as resolved (see `RunStart`)."""


@dataclass(frozen=True)
class PointsOutcome:
    """`seed-points active` after a round: points added away from the splat, or those a restart starts from."""

    added: int = 0
    restart: Optional[int] = None
    """The points a restart starts from (None: no restart triangulated)."""
    seconds: float = 0.0

    def fields(self) -> Dict[str, float]:
        """The round log's `after_add` entries."""
        if self.restart is not None:
            return {"seed_points_restart": float(self.restart), "seed_points_seconds": float(self.seconds)}
        return {"seed_points_added": float(self.added), "seed_points_seconds": float(self.seconds)}

    def recorded_in(self, record: Any) -> Any:
        """`record` (a `RoundRecord`) with these entries in its `after_add`."""
        return dataclasses.replace(record, after_add={**record.after_add, **self.fields()})


@dataclass(frozen=True)
class RoundAdded:
    """A round's add, as strategies see it right after (`after_round`)."""

    step: int
    end: int
    """The run's last step + 1."""
    views_before: int
    views_after: int
    optimizers: Any
    """The trainer's nerfstudio `Optimizers` (None: a test without a trainer)."""
    triangulate: Optional[Callable[[], Any]] = None
    """`seed-points active`: triangulate every active view now (the datamanager's `triangulate_active`: xyz, rgb,
    info); None for the other starts."""


class Strategy:
    """The hooks, all no-ops (see the module docstring)."""

    render_depth: bool = False

    def at_start(self, model: Any, start: RunStart) -> Union[None, str, Dict[str, str]]:
        config = getattr(self, "config", None)  # what its options say a resumed run must keep
        return config.describe() if isinstance(config, StrategyConfig) else None

    def plan(self, model: Any, plan: RoundsPlan) -> None:
        return None

    def after_round(self, model: Any, added: RoundAdded) -> Optional[Any]:
        return None

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
