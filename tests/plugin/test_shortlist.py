"""The shortlist: one selector keeps its best share of the candidates, another ranks exactly those; its options'
bad values and idle settings each give one line."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List

import pytest
import torch
from test_selector_maths import context

from hpgs_ns.errors import OptionError
from hpgs_ns.selection.config import SelectionConfig
from hpgs_ns.selectors import Selection, SelectionContext, SelectionError
from hpgs_ns.selectors.farthest import FarthestSelector, FarthestSelectorConfig
from hpgs_ns.selectors.random_views import RandomSelectorConfig
from hpgs_ns.selectors.shortlist import ShortlistSelector, shortlist_count


@dataclass
class LowestIndex:
    """Picks the lowest-numbered candidates and remembers what it was offered."""

    seen: List[List[int]] = field(default_factory=list)

    def select(self, ctx: SelectionContext) -> Selection:
        self.seen.append(list(ctx.candidates))
        picked = sorted(ctx.candidates)[: ctx.num_to_pick]
        return Selection(indices=picked, scores={c: -float(c) for c in ctx.candidates})


@pytest.mark.parametrize("size, pool, kept", [(0.2, 9, 2), (0.2, 10, 2), (0.2, 11, 3), (0.5, 3, 2), (1.0, 7, 7),
                                              (1e-6, 40, 1), (0.25, 8, 2)])
def test_shortlist_keeps_the_ceiling_of_its_share_and_at_least_one(size, pool, kept):
    assert shortlist_count(size, pool) == kept


def test_the_ranker_sees_exactly_the_shortlist_and_its_pick_is_the_rounds():
    ranker = LowestIndex()
    ctx = context(active=[0, 1, 11], candidates=range(2, 11), k=1)  # 9 candidates on a ring of 12
    selection = ShortlistSelector(FarthestSelectorConfig().setup(), ranker, 0.34).select(ctx)
    # farthest's greedy order from {0, 1, 11}: 6 (opposite), then 3 or 9, then the other side: ceil(0.34 * 9) = 4 views
    far = FarthestSelector(FarthestSelectorConfig()).select(context([0, 1, 11], range(2, 11), k=4)).indices
    assert len(ranker.seen) == 1 and sorted(ranker.seen[0]) == sorted(far) and len(far) == 4 and 6 in far
    assert ranker.seen[0] == sorted(far)  # in the candidates' own order
    assert selection.indices == [min(far)] and set(selection.scores) == set(far)
    assert selection.work["shortlist_kept"] == 4 and selection.work["shortlist_pool"] == 9


def test_a_shortlist_of_every_candidate_asks_the_shortlister_nothing():
    class Never:
        def select(self, ctx):
            raise AssertionError("the shortlist selector ran")

    ranker = LowestIndex()
    picked = ShortlistSelector(Never(), ranker, 1.0).select(context([0], range(1, 12), k=2)).indices
    assert picked == [1, 2] and ranker.seen == [list(range(1, 12))]


def test_a_shortlist_smaller_than_the_rounds_views_is_one_line():
    sel = ShortlistSelector(FarthestSelectorConfig().setup(), LowestIndex(), 0.2)
    with pytest.raises(SelectionError) as err:
        sel.select(context([0], range(1, 11), k=3))  # keeps 2 of 10, the round adds 3
    assert str(err.value) == ("--pipeline.selection.shortlist-size 0.2 keeps 2 of 10 candidates, fewer than the 3 views "
                              "this round adds; raise it to at least 0.30 or lower --pipeline.selection.views-per-round")


@pytest.mark.parametrize("size", [0.0, -0.1, 1.5, math.nan, math.inf])
def test_shortlist_size_outside_zero_one_is_one_line(size):
    with pytest.raises(OptionError) as err:
        SelectionConfig(shortlist="farthest", shortlist_size=size)
    assert str(err.value) == (f"--pipeline.selection.shortlist-size {size}: must be a share of the candidates in (0, 1]; "
                              "pass e.g. 0.2 (the best 20%)")


def test_an_unknown_shortlist_is_the_unknown_selector_line():
    with pytest.raises(OptionError) as err:
        SelectionConfig(shortlist="nosuch")
    assert str(err.value).startswith("--pipeline.selection.shortlist nosuch: unknown selector; choose one of random, "
                                     "farthest, fisher")


def test_idle_and_pointless_shortlist_options_say_so_and_random_stays_uniform():
    assert SelectionConfig(shortlist_size=0.3).shortlist_notes() == [
        "--pipeline.selection.shortlist-size 0.3 does nothing in this run: no shortlist (add "
        "--pipeline.selection.shortlist NAME)"]
    under_random = SelectionConfig(selector="random", shortlist="farthest")
    assert under_random.shortlist_notes() == [
        "--pipeline.selection.shortlist farthest changes nothing in this run: the selector is random, which picks "
        "uniformly from every candidate (it is the baseline)"]
    ctx = context([0], range(1, 12), k=3, seed=5)
    alone = RandomSelectorConfig().setup().select(ctx).indices
    assert under_random.build_selector().select(context([0], range(1, 12), k=3, seed=5)).indices == alone
    assert SelectionConfig(shortlist="farthest", shortlist_size=1.0).shortlist_notes()[0].endswith(
        "shortlist-size 1 keeps every candidate")
    assert SelectionConfig(shortlist="farthest", selector="fisher").shortlist_notes() == []
    assert SelectionConfig().shortlist_notes() == []


def test_the_shortlists_options_are_not_idle_and_its_settings_join_the_resume_signature():
    cfg = SelectionConfig(selector="random", shortlist="farthest")
    cfg.farthest.tie_tolerance = 0.01
    assert cfg.idle_selector_options() == []
    plain = SelectionConfig(selector="fisher").resume_signature(0)
    assert "shortlist" not in plain  # a checkpoint written before the option resumes unchanged
    shortlisted = SelectionConfig(selector="fisher", shortlist="farthest", shortlist_size=0.3).resume_signature(0)
    assert shortlisted["shortlist"] == "farthest" and shortlisted["shortlist-size"] == "0.3"
    assert shortlisted["farthest.tie-tolerance"] == "0.001"
    assert set(plain) < set(shortlisted)


def test_the_loop_shortlist_wraps_the_chosen_selector():
    cfg = SelectionConfig(selector="farthest", shortlist="random", shortlist_size=0.5)
    sel = cfg.build_selector()
    assert isinstance(sel, ShortlistSelector) and sel.size == 0.5
    ctx = context([0], range(1, 12), k=1, seed=3)
    kept = RandomSelectorConfig().setup().select(context([0], range(1, 12), k=6, seed=3)).indices
    picked = sel.select(ctx).indices
    # farthest among random's six: the one farthest from camera 0 among them
    centres = ctx.cameras.camera_to_worlds[:, :3, 3]
    best = max(kept, key=lambda c: float(torch.linalg.norm(centres[c] - centres[0])))
    assert picked == [best]
