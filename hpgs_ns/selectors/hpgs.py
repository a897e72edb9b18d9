"""`hpgs`: the HP-GS selector (human-preference features, cosine distance to the training set).

The preference model's feature extractor F embeds the current renders of the active views and of every
candidate. The candidate whose feature is farthest (cosine distance) from the element-wise *median* feature of
the active views is picked: O(n) model calls. The median rather than the mean because outlier views would drag
the mean (the paper, Sec. 3.3). `median-distance` is what the authors' code does instead: for each candidate the
median over active views of 1 - cos(f_candidate, f_active).

Input recipe (the same for the preference model's training renders and here): the model sees images whose
short side is its input size, aspect kept, no crop. Here views are rendered directly at that short side (cheaper
than a full render followed by a resize), batched in one rasterization call per 16 views, under no_grad.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Literal, Optional, Sequence, Type

import torch

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError
from hpgs_ns.selectors.preference_features import PreferenceSelectorConfig, load_preference_model, render_features


@dataclass
class HpgsSelectorConfig(PreferenceSelectorConfig):
    """HP-GS: largest cosine distance from the median preference feature of the active views."""

    _target: Type = field(default_factory=lambda: HpgsSelector)
    aggregate: Literal["median-feature", "median-distance"] = "median-feature"
    """`median-feature`: distance to the median feature (the paper). `median-distance`: median over active views
    of the distance (the authors' code)."""


class HpgsSelector:
    """Picks the candidates least like the training set in preference-feature space."""

    def __init__(self, config: HpgsSelectorConfig) -> None:
        self.config = config
        # Loaded now, so a missing or mismatched checkpoint fails at start-up, not at the first round.
        self.pref = load_preference_model(config.model)

    def features(self, context: SelectionContext, views: Sequence[int], work: Optional[dict] = None) -> torch.Tensor:
        return render_features(self.pref, context, views, self.config.render_short_side, self.config.batch_size, work)

    def select(self, context: SelectionContext) -> Selection:
        work: dict = {}
        active_f = self.features(context, context.active, work)
        cand_f = self.features(context, context.candidates, work)
        pool = list(context.candidates)
        picked: List[int] = []
        scores = {}
        for _ in range(context.num_to_pick):
            dist = cosine_distance_to_set(cand_f, active_f, self.config.aggregate)
            if not torch.isfinite(dist).all():
                raise SelectionError("hpgs: non-finite feature distance (NaN in a render or in the model)")
            if not picked:
                scores = {c: float(d) for c, d in zip(pool, dist)}
            for j in picked_positions(pool, picked):
                dist[j] = -torch.inf
            best = int(torch.argmax(dist))
            picked.append(pool[best])
            # Greedy batch: the pick's feature joins the training side before the next pick.
            active_f = torch.cat([active_f, cand_f[best : best + 1]])
        return Selection(indices=picked, scores=scores, work=work)


def picked_positions(pool: List[int], picked: List[int]) -> List[int]:
    return [pool.index(p) for p in picked]


def cosine_distance_to_set(cand: torch.Tensor, train: torch.Tensor, aggregate: str = "median-feature") -> torch.Tensor:
    """1 - cos between each candidate feature [M, F] and the training features [T, F] -> [M].

    `median-feature`: against the element-wise median of `train`; `median-distance`: median of the M x T
    distances over the training views."""
    cand = torch.nn.functional.normalize(cand.double(), dim=-1, eps=1e-12)
    if aggregate == "median-feature":
        # quantile(0.5) averages the two middle values for an even count (torch.median returns the lower one).
        centre = torch.nn.functional.normalize(torch.quantile(train.double(), 0.5, dim=0), dim=-1, eps=1e-12)
        return 1.0 - cand @ centre
    if aggregate == "median-distance":
        train = torch.nn.functional.normalize(train.double(), dim=-1, eps=1e-12)
        return torch.quantile(1.0 - cand @ train.T, 0.5, dim=1)
    raise ValueError(f"unknown aggregate {aggregate!r}")
