"""`condorcet`: the HP-GS paper's ablation: pairwise duels between candidates.

Every pair of candidates duels with the preference model's Bradley-Terry probability
p(i worse than j) = sigmoid(s_i - s_j); the candidate judged *worse* (more poorly reconstructed) in the most
duels is picked. The model is run once per image (n forwards) and the n(n-1)/2 duels are computed from the
scores. With Bradley-Terry the duels are transitive, so the winner is the highest-scoring candidate; the duels
are kept because that is the method being ablated (its O(n^2) cost is what the benchmark reports).
It ignores the training views entirely, which is the paper's argument against it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

import torch

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError
from hpgs_ns.selectors.preference_features import PreferenceSelectorConfig, load_preference_model, render_scores


@dataclass
class CondorcetSelectorConfig(PreferenceSelectorConfig):
    """Condorcet winner of Bradley-Terry duels between candidates (the one judged worse most often)."""

    _target: Type = field(default_factory=lambda: CondorcetSelector)
    max_candidates: int = 0
    """Duel only a random subset of this many candidates (0 = all)."""


def duel_wins(scores: torch.Tensor) -> torch.Tensor:
    """Number of duels each candidate loses on quality (is judged worse): [M] -> [M].

    p(i worse than j) = sigmoid(s_i - s_j) > 1/2, ties count half."""
    p_worse = torch.sigmoid(scores[:, None] - scores[None, :])
    wins = (p_worse > 0.5).double() + 0.5 * (p_worse == 0.5).double()
    wins.fill_diagonal_(0)
    return wins.sum(dim=1)


class CondorcetSelector:
    """Pairwise Bradley-Terry duels; the most-often-worse candidate wins."""

    def __init__(self, config: CondorcetSelectorConfig) -> None:
        self.config = config
        self.pref = load_preference_model(config.model)

    def select(self, context: SelectionContext) -> Selection:
        pool = list(context.candidates)
        cap = self.config.max_candidates
        if cap and len(pool) > cap:
            keep = torch.randperm(len(pool), generator=context.generator)[:cap].sort().values.tolist()
            pool = [pool[i] for i in keep]
        work: dict = {}
        s = render_scores(self.pref, context, pool, self.config.render_short_side, self.config.batch_size, work).double()
        if not torch.isfinite(s).all():
            raise SelectionError("condorcet: non-finite preference score (NaN in a render or in the model)")
        wins = duel_wins(s)
        # Most duels judged worse first; the BT score breaks ties in win counts.
        order = sorted(range(len(pool)), key=lambda i: (float(wins[i]), float(s[i])), reverse=True)
        picked = [pool[i] for i in order[: context.num_to_pick]]
        work["duels"] = len(pool) * (len(pool) - 1) // 2
        return Selection(indices=picked, scores={pool[i]: float(wins[i]) for i in range(len(pool))}, work=work)
