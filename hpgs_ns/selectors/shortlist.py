"""A shortlist that composes two selectors: one keeps its best share of the candidates, the other ranks only those.

SA-ResGS (arXiv 2601.03024) keeps the 20% of candidates least like the training views' coverage before FisherRF;
AGILE-GS+ reranks a geometric shortlist with Fisher information. Here either selector can be any registered one:
`--pipeline.selection.shortlist NAME --pipeline.selection.shortlist-size FRACTION` wraps the run's selector, and
the presets in `hpgs_ns.selectors.presets` (e.g. `farthest-dopt`) are such pairs under one name.

The shortlisting selector picks `ceil(FRACTION x candidates)` views (its greedy order: `farthest` keeps a spread of
far views, `fisher` its most informative), once a round; the ranking selector then picks the round's views from
them with the round's own generator state, so a resumed run makes the same choices.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Type

from hpgs_ns.errors import check_option
from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, Selector, SelectorConfig


def shortlist_count(size: float, candidates: int) -> int:
    """How many of `candidates` a shortlist of share `size` (0 < size <= 1) keeps: at least one."""
    return max(1, min(candidates, math.ceil(size * candidates - 1e-9)))


def check_shortlist_size(flag: str, size: float) -> None:
    """One line unless 0 < size <= 1."""
    check_option(flag, size, math.isfinite(size) and 0 < size <= 1,
                 "must be a share of the candidates in (0, 1]", "pass e.g. 0.2 (the best 20%)")


class ShortlistSelector:
    """`first` keeps its best `size` share of the candidates; `then` picks the round's views among them."""

    def __init__(self, first: Selector, then: Selector, size: float, first_name: str = "shortlist",
                 flag: str = "--pipeline.selection.shortlist-size") -> None:
        self.first, self.then, self.size = first, then, float(size)
        self.first_name, self.flag = first_name, flag

    def select(self, context: SelectionContext) -> Selection:
        count = shortlist_count(self.size, len(context.candidates))
        if count < context.num_to_pick:
            raise SelectionError(
                f"{self.flag} {self.size:g} keeps {count} of {len(context.candidates)} candidates, fewer than the "
                f"{context.num_to_pick} views this round adds; raise it to at least "
                f"{context.num_to_pick / len(context.candidates):.2f} or lower --pipeline.selection.views-per-round")
        if count == len(context.candidates):
            short = Selection(indices=list(context.candidates))
        else:
            short = self.first.select(dataclasses.replace(context, num_to_pick=count))
        kept = [int(i) for i in short.indices]
        if len(set(kept)) != count or not set(kept) <= set(context.candidates):
            raise SelectionError(f"shortlist selector {self.first_name} returned {len(kept)} views, not {count} distinct "
                                 "candidates")
        # The ranker sees the shortlist in the candidates' own order, so its ties break as they would without it.
        order = [c for c in context.candidates if c in set(kept)]
        picked = self.then.select(dataclasses.replace(context, candidates=order))
        work = {**{f"shortlist_{k}": v for k, v in short.work.items()}, **picked.work,
                "shortlist_kept": float(count), "shortlist_pool": float(len(context.candidates))}
        return Selection(indices=list(picked.indices), scores=dict(picked.scores), work=work)


@dataclass
class ShortlistPresetConfig(SelectorConfig):
    """A shortlist pair under one selector name: `first`'s best `shortlist_size` share of the candidates, ranked by
    `then`. Presets subclass it with concrete `first`/`then` types (their options become flags)."""

    _target: Type = field(default_factory=lambda: ShortlistSelector)
    shortlist_size: float = 0.2
    """Share of the candidates the first selector keeps for the second to rank (0 < share <= 1)."""
    logged_in_candidate_log = False  # its scores are its ranker's, over a shortlist only

    def __post_init__(self) -> None:
        check_shortlist_size(f"--pipeline.selection.{self.preset_name()}.shortlist-size", self.shortlist_size)

    @classmethod
    def preset_name(cls) -> str:
        """The name the registry gives this preset (its flags' group)."""
        from hpgs_ns.selectors.registry import name_of

        return name_of(cls) or "preset"

    def setup(self, **kwargs) -> Selector:
        first, then = self.first, self.then  # type: ignore[attr-defined]
        return ShortlistSelector(first.setup(), then.setup(), self.shortlist_size, type(first).__name__,
                                 f"--pipeline.selection.{self.preset_name()}.shortlist-size")
