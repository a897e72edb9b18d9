"""Selectors on a scene where the answer is known: the splat is trained only on views of one side.

The tiny `ring` scene is trained (strict init: only seed points seen by the active views) on the views within
60 degrees of azimuth 0; the other side is seen by no active view. `fisher`, `hpgs` (with a small preference
model trained here to find blurred images worse) and `farthest` must pick a view of the unseen side.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch
from conftest import short_config
from PIL import Image, ImageFilter

from hpgs_ns.selectors import SelectionError
from hpgs_ns.selectors.farthest import FarthestSelectorConfig
from hpgs_ns.selectors.fisher import FisherSelectorConfig
from hpgs_ns.selectors.hpgs import HpgsSelectorConfig
from hpgs_ns.selectors.random_views import RandomSelectorConfig


def azimuths(scene: Path) -> dict:
    gt = json.loads((scene / "ground_truth.json").read_text())
    return {f"images/{c['name']}": c["azimuth_deg"] for c in gt["cameras"]}  # by view name


def angular_distance(a: float, b: float) -> float:
    d = abs(a - b) % 360
    return min(d, 360 - d)


@pytest.fixture(scope="module")
def one_sided(tiny_scene, tmp_path_factory):
    az = azimuths(tiny_scene)
    test = {f"images/{i:04d}.png" for i in range(0, 40, 8)}
    side = tuple(sorted(n for n, a in az.items() if angular_distance(a, 0) <= 60 and n not in test))
    cfg = short_config(tiny_scene, tmp_path_factory.mktemp("one-sided"), steps=40, rounds=0,
                       initial_view_names=side)
    cfg.set_timestamp()
    cfg.save_config()
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    return trainer, az


def pick(trainer, selector_config, name: str, k: int = 1):
    dm, rounds = trainer.pipeline.datamanager, trainer.pipeline.rounds
    saved = (list(dm.active), list(dm.history), rounds.selector, rounds.config.views_per_round, rounds.config.selector)
    rounds.selector, rounds.config.views_per_round = selector_config.setup(), k
    try:
        selection = rounds.run_round(1000 + len(dm.history))
        return [dm.image_names[i] for i in selection.indices], selection
    finally:
        dm.active, dm.history, rounds.selector, rounds.config.views_per_round, rounds.config.selector = saved


def assert_unseen_side(names, az):
    for name in names:
        assert angular_distance(az[name], 0) >= 100, f"{name} at azimuth {az[name]:.0f} is on the trained side"


def test_farthest_picks_the_unseen_side(one_sided):
    trainer, az = one_sided
    names, _ = pick(trainer, FarthestSelectorConfig(), "farthest")
    assert_unseen_side(names, az)


def test_fisher_picks_the_unseen_side_and_batches_without_repeats(one_sided):
    trainer, az = one_sided
    names, selection = pick(trainer, FisherSelectorConfig(probes=4, train_probe_factor=2, view_batch=8), "fisher", k=2)
    assert_unseen_side(names[:1], az)
    assert len(set(names)) == 2
    assert all(math.isfinite(s) for s in selection.scores.values())
    # Work done and skipped: half-resolution renders, frustum-culled pairs, one backward per probe per batch of 8.
    dm = trainer.pipeline.datamanager
    n_active, n_cand = len(dm.active), len(dm.candidates)
    batches = lambda n: -(-n // 8)  # noqa: E731
    work = selection.work
    assert work["pixels_rendered"] == 0.25 * work["pixels_full_resolution"]
    assert 0 < work["pairs_differentiated"] < work["pairs_unculled"]
    assert work["backward_passes"] == 8 * batches(n_active) + 4 * batches(n_cand) + 8 + 4 * batches(n_cand - 1)
    assert work["views_rendered"] == n_active + n_cand + 1 + (n_cand - 1)


def test_hpgs_with_a_blur_preferring_model_picks_the_unseen_side(one_sided, tiny_scene, tmp_path):
    from hpgs_ns.preference.train import TrainPref

    # A preference model that learned "blurred is worse" from 24 photo/blurred-photo pairs.
    pairs_dir = tmp_path / "pairs"
    pairs_dir.mkdir()
    rows = []
    for k, path in enumerate(sorted((tiny_scene / "images").glob("*.png"))[:24]):
        sharp = Image.open(path).convert("RGB").resize((128, 96))
        sharp.save(pairs_dir / f"sharp{k}.png")
        sharp.filter(ImageFilter.GaussianBlur(3)).save(pairs_dir / f"blur{k}.png")
        rows.append((f"sharp{k}.png", f"blur{k}.png", 0) if k % 2 else (f"blur{k}.png", f"sharp{k}.png", 1))
    with open(pairs_dir / "pairs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Image_1", "Image_2", "Human Preference"])
        w.writerows(rows)
    model_path = tmp_path / "blur.pt"
    TrainPref(pairs=(pairs_dir / "pairs.csv",), out=model_path, backbone="alexnet", input_size=96, test_fraction=0.0).main()

    trainer, az = one_sided
    names, selection = pick(trainer, HpgsSelectorConfig(model=model_path, render_short_side=48), "hpgs", k=2)
    assert_unseen_side(names[:1], az)
    assert len(set(names)) == 2
    assert len(selection.scores) == len(trainer.pipeline.datamanager.candidates)


@pytest.mark.shipped_model  # the shipped model's 224-pixel input, and one selection with it
def test_preference_selectors_render_small_views_as_they_are_and_large_ones_at_the_model_size(one_sided):
    from hpgs_ns.selectors.preference_features import _render_short_side

    trainer, _ = one_sided
    # 64x48 views, below the shipped model's 224-pixel input: rendered at their own size, not upsampled.
    names, selection = pick(trainer, HpgsSelectorConfig(), "hpgs")
    assert selection.work["pixels_rendered"] == selection.work["pixels_full_resolution"] > 0
    pref = HpgsSelectorConfig().setup().pref
    cameras = trainer.pipeline.datamanager.train_dataset.cameras[:2]
    assert _render_short_side(pref, None, cameras) is None
    cameras.rescale_output_resolution(10.0)  # 640x480
    assert _render_short_side(pref, None, cameras) == pref.input_size == 224
    assert _render_short_side(pref, 32, cameras) == 32  # an explicit size wins


def test_random_follows_seed_and_empty_pool_ends_selection(one_sided):
    trainer, _ = one_sided
    a, _ = pick(trainer, RandomSelectorConfig(), "random", k=3)
    b, _ = pick(trainer, RandomSelectorConfig(), "random", k=3)
    assert a == b and len(set(a)) == 3
    dm, rounds = trainer.pipeline.datamanager, trainer.pipeline.rounds
    saved = list(dm.active)
    dm.active = list(range(len(dm.train_dataset)))  # pool exhausted
    try:
        assert not rounds.is_round_step(2 * rounds.config.select_every)
        with pytest.raises(SelectionError, match="no withheld views"):
            rounds.run_round(123)
    finally:
        dm.active = saved


def test_missing_preference_model_fails_at_startup(tmp_path):
    with pytest.raises(SelectionError, match="not found"):
        HpgsSelectorConfig(model=tmp_path / "nope.pt").setup()
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(SelectionError) as err:
        HpgsSelectorConfig(model=bad).setup()
    # the path and the fix once (the loader's own line, not wrapped in a second)
    assert str(err.value) == f"{bad}: not a readable checkpoint (UnpicklingError); retrain with `hpgs train-pref`"


def spearman(a, b) -> float:
    ra = torch.tensor(a).argsort().argsort().double()
    rb = torch.tensor(b).argsort().argsort().double()
    ra, rb = ra - ra.mean(), rb - rb.mean()
    return float((ra * rb).sum() / (ra.norm() * rb.norm()))


def test_fisher_probe_ranking_matches_exact_at_default_k(one_sided):
    """K=16 Rademacher probes rank candidates like the exact per-pixel diagonal (16x12 renders)."""
    trainer, az = one_sided
    dm, rounds = trainer.pipeline.datamanager, trainer.pipeline.rounds
    active = sorted(dm.active)[::4][:2]
    candidates = [i for i in range(len(dm.train_dataset)) if i not in dm.active][:8]
    scores = {}
    for mode in ("exact", "probe"):
        ctx = rounds.context(500)
        ctx.active, ctx.candidates, ctx.num_to_pick = active, candidates, 1
        selector = FisherSelectorConfig(mode=mode, resolution_scale=0.25).setup()
        scores[mode] = selector.select(ctx).scores
    exact = [scores["exact"][c] for c in candidates]
    probe = [scores["probe"][c] for c in candidates]
    assert spearman(exact, probe) >= 0.9, (exact, probe)


def test_blend_scores_are_farthest_and_hpgs_scores_combined_through_ns_train_options(one_sided):
    from hpgs_ns.selectors.blend import BlendSelectorConfig

    trainer, az = one_sided
    _, far = pick(trainer, FarthestSelectorConfig(), "farthest")
    _, pref = pick(trainer, HpgsSelectorConfig(), "hpgs")
    names, selection = pick(trainer, BlendSelectorConfig(farthest_weight=2.0, hpgs_weight=1.0), "blend")
    z = lambda s: (s - s.mean()) / s.std(unbiased=False)  # noqa: E731
    cand = sorted(selection.scores)
    expected = 2.0 * z(torch.tensor([far.scores[c] for c in cand], dtype=torch.float64)) + z(
        torch.tensor([pref.scores[c] for c in cand], dtype=torch.float64))
    assert [selection.scores[c] for c in cand] == pytest.approx(expected.tolist(), abs=1e-6)
    assert names == [trainer.pipeline.datamanager.image_names[cand[int(expected.argmax())]]]
    assert_unseen_side(names, az)  # coverage weighs double here
    assert type(trainer.pipeline.config.selection.blend) is BlendSelectorConfig  # an ns-train option group


def test_presets_pick_the_unseen_side_and_rank_only_their_shortlist(one_sided):
    from hpgs_ns.selectors.presets import FarthestDoptSelectorConfig, FisherDoptSelectorConfig

    trainer, az = one_sided
    light = dict(probes=4, train_probe_factor=2, view_batch=8)
    names, selection = pick(trainer, FisherDoptSelectorConfig(**light), "fisher-dopt")
    assert_unseen_side(names, az)
    # D-optimal scores are log-gains: positive, and below the trace's (log(1 + x) < x)
    trace = pick(trainer, FisherSelectorConfig(**light), "fisher")[1].scores
    assert all(0 < s for s in selection.scores.values()) and sum(selection.scores.values()) < sum(trace.values())
    dm = trainer.pipeline.datamanager
    pool = len(dm.candidates)
    # coverage shortlisting for fisher: the shortlist option, as a preset would set it
    from types import SimpleNamespace

    from hpgs_ns.selectors.coverage import CoverageSelectorConfig
    from hpgs_ns.selectors.shortlist import ShortlistSelector

    coverage_fisher = SimpleNamespace(setup=lambda: ShortlistSelector(CoverageSelectorConfig().setup(),
                                                                      FisherSelectorConfig(**light).setup(), 0.2, "coverage"))
    for name, preset in (("farthest-dopt", FarthestDoptSelectorConfig(then=FisherSelectorConfig(criterion="dopt", **light))),
                         ("coverage-fisher", coverage_fisher)):
        names, selection = pick(trainer, preset, name)
        assert_unseen_side(names, az)
        kept = math.ceil(0.2 * pool)
        assert selection.work["shortlist_kept"] == kept and len(selection.scores) == kept
