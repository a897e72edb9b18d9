"""Selector maths that needs no rendering: farthest-point choice, cosine distances, Condorcet duels, validation."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras

from hpgs_ns.selectors import RandomSelectorConfig, Selection, SelectionContext, SelectionError, check_selection
from hpgs_ns.selectors.condorcet import duel_wins
from hpgs_ns.selectors.farthest import FarthestSelectorConfig
from hpgs_ns.selectors.hpgs import cosine_distance_to_set


def ring_cameras(n: int = 12, radius: float = 3.0) -> Cameras:
    """n cameras on a circle, each looking at the origin (nerfstudio convention: looks along -z)."""
    c2w = []
    for k in range(n):
        a = 2 * math.pi * k / n
        centre = torch.tensor([radius * math.cos(a), radius * math.sin(a), 0.0])
        back = centre / centre.norm()  # -forward
        up = torch.tensor([0.0, 0.0, 1.0])
        right = torch.linalg.cross(up, back)
        right = right / right.norm()
        true_up = torch.linalg.cross(back, right)
        c2w.append(torch.stack([right, true_up, back, centre], dim=1))
    return Cameras(camera_to_worlds=torch.stack(c2w), fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)


def context(active, candidates, k=1, seed=0) -> SelectionContext:
    cams = ring_cameras()
    return SelectionContext(
        step=100, round_index=0, active=list(active), candidates=list(candidates), num_to_pick=k, cameras=cams,
        image_names=[f"{i:03d}.png" for i in range(len(cams))], model=None, render=None,  # type: ignore[arg-type]
        generator=torch.Generator().manual_seed(seed),
    )


def test_farthest_picks_the_opposite_side_and_batches_greedily():
    sel = FarthestSelectorConfig().setup()
    ctx = context(active=[0, 1, 11], candidates=range(2, 11), k=2)
    picked = sel.select(ctx).indices
    assert picked[0] == 6  # diametrically opposite the active arc around camera 0
    # The second pick is farthest from {0, 1, 11, 6}: cameras 3/4 or 8/9, not next to 6.
    assert picked[1] in (3, 4, 8, 9)
    assert len(set(picked)) == 2


def test_random_follows_its_seed_and_never_repeats():
    sel = RandomSelectorConfig().setup()
    a = sel.select(context([0], range(1, 12), k=3, seed=7)).indices
    b = sel.select(context([0], range(1, 12), k=3, seed=7)).indices
    c = sel.select(context([0], range(1, 12), k=3, seed=8)).indices
    assert a == b and len(set(a)) == 3 and set(a) <= set(range(1, 12))
    assert a != c


def test_cosine_distance_to_median_feature_and_median_distance():
    train = torch.tensor([[1.0, 0.0], [1.0, 0.1], [1.0, -0.1], [0.0, 1.0]])  # one outlier
    cand = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    d = cosine_distance_to_set(cand, train, "median-feature")
    # median feature is (1, 0.05): the outlier does not drag it (a mean would).
    centre = torch.tensor([1.0, 0.05]) / torch.tensor([1.0, 0.05]).norm()
    expected = 1 - torch.nn.functional.normalize(cand, dim=-1) @ centre
    assert torch.allclose(d.float(), expected, atol=1e-6)
    assert int(torch.argmax(d)) == 2
    dm = cosine_distance_to_set(cand, train, "median-distance")
    assert dm.shape == (3,) and int(torch.argmax(dm)) == 2
    expected = float(torch.quantile(1 - torch.nn.functional.normalize(train, dim=-1)[:, 0].double(), 0.5))
    assert float(dm[0]) == pytest.approx(expected, abs=1e-6)


def test_condorcet_winner_equals_highest_bt_score():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        scores = torch.randn(15, generator=g, dtype=torch.float64)
        wins = duel_wins(scores)
        assert int(torch.argmax(wins)) == int(torch.argmax(scores))  # the WORST-judged one wins
        assert float(wins.max()) == 14  # beats everyone: BT duels are transitive
        assert float(wins.sum()) == 15 * 14 / 2


def test_check_selection_rejects_repeats_non_candidates_and_nan():
    ctx = context([0], [1, 2, 3], k=2)
    assert check_selection(Selection([1, 2], {1: 0.5}), ctx).indices == [1, 2]
    with pytest.raises(SelectionError, match="repeated or not candidates"):
        check_selection(Selection([1, 1]), ctx)
    with pytest.raises(SelectionError, match="repeated or not candidates"):
        check_selection(Selection([0, 1]), ctx)
    with pytest.raises(SelectionError, match="non-finite"):
        check_selection(Selection([1, 2], {1: float("nan")}), ctx)
    with pytest.raises(SelectionError, match="expected 2"):
        check_selection(Selection([1]), ctx)


class FixedFeatures:
    """Stands in for blend's hpgs part: a fixed feature per view, no rendering."""

    def __init__(self, features: torch.Tensor) -> None:
        self.table = features

    def features(self, context, views, work=None):
        return self.table[list(views)]


def blend(farthest_weight: float, hpgs_weight: float, features: torch.Tensor):
    from hpgs_ns.selectors.blend import BlendSelector, BlendSelectorConfig

    sel = BlendSelector.__new__(BlendSelector)  # skip loading the shipped preference model: features are fixed here
    sel.config = BlendSelectorConfig(farthest_weight=farthest_weight, hpgs_weight=hpgs_weight)
    sel.hpgs = FixedFeatures(features)
    return sel


def test_blend_is_the_weighted_sum_of_z_scored_coverage_and_feature_distance():
    from hpgs_ns.selectors.farthest import nearest_centre_distance

    # Active views look alike (feature e0); candidate 3 looks most different, 6 is farthest away, and 5 is second
    # in both: the compromise.
    feats = torch.zeros(12, 3)
    feats[:, 0] = 1.0
    feats[3] = torch.tensor([0.0, 1.0, 0.0])
    feats[5] = torch.tensor([0.2, 0.98, 0.0])
    ctx = context(active=[0, 1, 11], candidates=range(2, 11))
    assert blend(1.0, 0.0, feats).select(ctx).indices == FarthestSelectorConfig().setup().select(ctx).indices == [6]
    assert blend(0.0, 1.0, feats).select(ctx).indices == [3]
    # Equal weights: by hand, z(coverage) + z(feature distance) over the nine candidates.
    cand = list(range(2, 11))
    cov = nearest_centre_distance(ctx.cameras, cand, [0, 1, 11]).numpy()
    app = cosine_distance_to_set(feats[cand], feats[[0, 1, 11]]).numpy()
    total = (cov - cov.mean()) / cov.std() + (app - app.mean()) / app.std()
    selection = blend(1.0, 1.0, feats).select(ctx)
    assert selection.indices == [cand[int(total.argmax())]] == [5]
    assert [selection.scores[c] for c in cand] == pytest.approx(list(total))


def test_blend_batches_greedily_and_rejects_zero_weights():
    from hpgs_ns.selectors.blend import BlendSelectorConfig

    feats = torch.eye(12)
    ctx = context(active=[0, 1, 11], candidates=range(2, 11), k=3)
    picked = blend(1.0, 0.0, feats).select(ctx).indices
    assert picked == FarthestSelectorConfig().setup().select(ctx).indices[:1] + picked[1:] and len(set(picked)) == 3
    assert picked[1] in (3, 4, 8, 9)  # the first pick joined the active side
    with pytest.raises(SelectionError, match="blend: farthest-weight and hpgs-weight are both 0"):
        BlendSelectorConfig(farthest_weight=0.0, hpgs_weight=0.0).setup()
