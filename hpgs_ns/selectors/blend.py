"""`blend`: camera coverage and preference features together (`farthest` + `hpgs`, z-scored, weighted).

Each candidate gets farthest's score (distance from its camera centre to the nearest active one) and hpgs's
(cosine distance of its preference feature to the active views' median feature); each is z-scored over the
candidates of the round and the weighted sum picks. The weights come from offline logs, not GPU sweeps:
`hpgs bench --log-candidate-scores` records every selector's score of every candidate beside the candidate's
render error against its withheld photo, and an offline fit, leave one scene out, picks the weights that best
predict that error (how well they do: docs/selectors.md, `blend`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Dict, List, Tuple, Type

import torch

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError
from hpgs_ns.selectors.farthest import nearest_centre_distance
from hpgs_ns.selectors.hpgs import HpgsSelectorConfig, cosine_distance_to_set
from hpgs_ns.selectors.preference_features import PreferenceSelectorConfig


@dataclass
class BlendSelectorConfig(PreferenceSelectorConfig):
    """Weighted sum of farthest's and hpgs's z-scored scores (weights fitted on candidate logs)."""

    _target: Type = field(default_factory=lambda: BlendSelector)
    code_files: ClassVar[Tuple[str, ...]] = PreferenceSelectorConfig.code_files + ("selectors/farthest.py", "selectors/hpgs.py")
    # A fitted mix of farthest and hpgs, which the log records: logging it too would feed its own fit.
    logged_in_candidate_log: ClassVar[bool] = False
    # The weights an offline fit of farthest and hpgs sets: each one's option.
    fitted_weights: ClassVar[Dict[str, str]] = {"farthest": "farthest_weight", "hpgs": "hpgs_weight"}
    # Fitted on the candidate logs of four benchmark scenes (fox, juice box, gold cape, campus; FisherRF protocol, seed 1).
    farthest_weight: float = 0.437
    """Weight of the z-scored camera-centre distance."""
    hpgs_weight: float = 0.432
    """Weight of the z-scored preference-feature distance."""


def zscore(x: torch.Tensor) -> torch.Tensor:
    sd = x.std(unbiased=False)
    return (x - x.mean()) / sd if sd > 0 else torch.zeros_like(x)


class BlendSelector:
    """Greedy: each pick joins the active side (its centre and its feature) before the next one is scored."""

    def __init__(self, config: BlendSelectorConfig) -> None:
        if config.farthest_weight == 0 and config.hpgs_weight == 0:
            raise SelectionError("blend: farthest-weight and hpgs-weight are both 0; give at least one a weight")
        self.config = config
        self.hpgs = HpgsSelectorConfig(
            model=config.model, batch_size=config.batch_size, render_short_side=config.render_short_side).setup()

    def select(self, context: SelectionContext) -> Selection:
        work: dict = {}
        active_f = self.hpgs.features(context, context.active, work)
        cand_f = self.hpgs.features(context, context.candidates, work)
        pool = list(context.candidates)
        remaining = list(range(len(pool)))
        side = list(context.active)
        picked: List[int] = []
        scores = {}
        for _ in range(context.num_to_pick):
            views = [pool[j] for j in remaining]
            coverage = nearest_centre_distance(context.cameras, views, side)
            appearance = cosine_distance_to_set(cand_f[remaining], active_f)
            if not torch.isfinite(appearance).all():
                raise SelectionError("blend: non-finite feature distance (NaN in a render or in the model)")
            total = self.config.farthest_weight * zscore(coverage) + self.config.hpgs_weight * zscore(appearance)
            if not picked:
                scores = {v: float(s) for v, s in zip(views, total)}
            best = remaining.pop(int(torch.argmax(total)))
            picked.append(pool[best])
            side.append(pool[best])
            active_f = torch.cat([active_f, cand_f[best : best + 1]])
        return Selection(indices=picked, scores=scores, work=work)
