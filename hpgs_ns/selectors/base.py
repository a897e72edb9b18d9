"""The selector interface: one typed context in, the chosen candidate indices (and their scores) out.

The datamanager owns *which views are active*; a selector owns *how to score*; the model owns *rendering*.
A selector never edits the datamanager's lists: it reads the context and returns a `Selection`. Each selector's
options are a `SelectorConfig` whose `setup()` returns the selector; `hpgs_ns.selectors.registry` maps names to
them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, ClassVar, Dict, List, Optional, Protocol, Sequence, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.models.base_model import Model

from hpgs_ns.errors import UserError


class SelectionError(UserError, RuntimeError):
    """A selector cannot choose (bad options, empty pool, non-finite scores)."""


RenderFn = Callable[[Sequence[int], Optional[int]], List[torch.Tensor]]
"""render(indices, short_side) -> one [H, W, 3] image in [0, 1] per index, rendered in eval mode without grad.
`short_side=None` renders at the dataset's resolution; otherwise the camera is rescaled so min(H, W) = short_side."""


@dataclass
class SelectionContext:
    """What a selector may look at when it chooses the next views."""

    step: int
    """Training step at which the round happens."""
    round_index: int
    """0 for the first round."""
    active: List[int]
    """Indices (into the training split) of the views trained on so far."""
    candidates: List[int]
    """Indices of the withheld training views that may be added. Never includes test views."""
    num_to_pick: int
    """How many candidates to return (views-per-round, capped by the pool size)."""
    cameras: Cameras
    """All training-split cameras ([N_train]); index with `active`/`candidates`."""
    image_names: List[str]
    """File names of the training-split images, by index."""
    model: Model
    """The splat being trained (read-only for selectors): `render` for images; the hpgs model's `splat()`,
    `eval_mode()` and `active_sh_degree` for its tensors."""
    render: RenderFn
    """Renders views of the current splat (see `RenderFn`)."""
    generator: torch.Generator
    """Seeded random generator for any randomness the selector needs."""
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    progress: Callable[[int], None] = field(default=lambda views: None)
    """Call with the number of views just rendered: the round shows a progress bar of them (a CPU round can take
    minutes). Selectors that render nothing never call it."""


@dataclass
class Selection:
    """A selector's answer."""

    indices: List[int]
    """Chosen candidate indices, in the order they were picked."""
    scores: Dict[int, float] = field(default_factory=dict)
    """Score of every candidate looked at (higher = more wanted), for logging."""
    work: Dict[str, float] = field(default_factory=dict)
    """What the round computed and what it skipped (counts for the round log and the benchmark), e.g.
    `pixels_rendered` vs `pixels_full_resolution`, or `pairs_differentiated` vs `pairs_unculled`."""


class Selector(Protocol):
    """Chooses the next views to train on."""

    def select(self, context: SelectionContext) -> Selection:
        """Return `context.num_to_pick` distinct indices from `context.candidates`."""
        ...


@dataclass
class SelectorConfig(InstantiateConfig):
    """A selector's options (typed fields become `--pipeline.selection.<name>.<option>` flags); `setup()`
    builds the selector (its `_target`) with them.

    The class variables are the selector's facts that the rest of the package reads (the benchmark, provenance,
    the candidate log), so a selector registered by another package needs no edit here."""

    uses_preference_model: ClassVar[bool] = False
    """Scores views with a preference model (`hpgs bench --preference-models` gives it each scene's
    leave-one-scene-out model; provenance records the model's hash)."""
    code_files: ClassVar[Tuple[str, ...]] = ()
    """Files (relative to the `hpgs_ns` package) besides the selector's own module whose change can move its
    numbers (the benchmark's code hash)."""
    logged_in_candidate_log: ClassVar[bool] = True
    """Whether `--pipeline.selection.log-candidate-scores` records this selector's score of every candidate."""
    ranks_a_shortlist: ClassVar[bool] = True
    """Whether `--pipeline.selection.shortlist` applies under this selector (a uniform baseline ranks every candidate)."""
    fitted_weights: ClassVar[Dict[str, str]] = {}
    """Options fitted offline on candidate logs, {selector whose z-scored score it weighs: the option of its weight}:
    a fit names each weight by the selector it weighs, and this maps that name to the option to set."""

    def setup(self, **kwargs) -> Selector:
        return super().setup(**kwargs)


def check_selection(selection: Selection, context: SelectionContext) -> Selection:
    """Validate a selector's answer: distinct candidates, the right count, finite scores."""
    picked = list(selection.indices)
    pool = set(context.candidates)
    if len(picked) != min(context.num_to_pick, len(pool)):
        raise SelectionError(f"selector returned {len(picked)} views, expected {context.num_to_pick}")
    if len(set(picked)) != len(picked) or not set(picked) <= pool:
        raise SelectionError(f"selector returned views that are repeated or not candidates: {picked}")
    bad = [i for i, s in selection.scores.items() if not torch.isfinite(torch.tensor(float(s)))]
    if bad:
        raise SelectionError(f"selector produced non-finite scores for views {bad[:5]}")
    return selection
