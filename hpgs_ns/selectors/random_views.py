"""`random`: the baseline every view-selection paper compares against."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Type

import torch

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectorConfig


@dataclass
class RandomSelectorConfig(SelectorConfig):
    """Uniformly random candidates, drawn from the datamanager's seeded generator (so `--seed` fixes them)."""

    _target: Type = field(default_factory=lambda: RandomSelector)
    # Its scores are all equal: nothing for the candidate log to record.
    logged_in_candidate_log: ClassVar[bool] = False
    # The uniform baseline draws from every candidate: a shortlist would make it another selector.
    ranks_a_shortlist: ClassVar[bool] = False


class RandomSelector:
    """Picks candidates uniformly at random without replacement."""

    def __init__(self, config: RandomSelectorConfig) -> None:
        self.config = config

    def select(self, context: SelectionContext) -> Selection:
        order = torch.randperm(len(context.candidates), generator=context.generator).tolist()
        picked = [context.candidates[i] for i in order[: context.num_to_pick]]
        return Selection(indices=picked, scores={i: 0.0 for i in context.candidates})
