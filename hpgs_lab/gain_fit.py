"""The early-stop calibration, fitted on benchmark runs: what a view is worth, and what stopping would cost.

What a view is worth. The test PSNR of a run rises with training as much as with views, so the change from one
round to the next says little about the view. With `eval-each-round` every run records its test PSNR at every
round step (`RunResult.psnr_at_round_steps`), the `initial` reference too, which trains the same steps on the
initial views alone. The cumulative gain of a run's views at step s is G(s) = PSNR(s) - PSNR_initial(s) (same
seed, same steps), and round k's view gained G(s_k+1) - G(s_k), the training between the two being the same
for both runs.

The model (`GainModel`, used at run time by `stop-when-gain-below`) calibrates that marginal gain against the
number of views, per selector: gain = a + b * log(views), fitted here (`fit_gain_model`) and judged leave one
scene out (`early_stop_curve`, which also estimates what stopping at round k costs as G(end) - G(s_k)). A
selector the model does not know uses the average over selectors (so does `random`, which has no score).
`benchmarks/early_stop.py` fits the shipped model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from hpgs_lab.names import INITIAL
from hpgs_lab.results import RunResult
from hpgs_ns.selection.early_stop import ALL, GainModel


@dataclass(frozen=True)
class ViewGain:
    """One run's views before each round (`views`) and the cumulative gain G of its added views at each round
    step and at the end (`G` lists one more value than `views`)."""

    run: RunResult
    views: List[int]
    G: List[float]

    @property
    def scene(self) -> str:
        return self.run.scene

    @property
    def selector(self) -> str:
        return self.run.selector


def view_gains(rows: Iterable[RunResult]) -> List[ViewGain]:
    """Per run with a matching `initial` reference, both with their test PSNR at the round steps, its `ViewGain`.
    The reference is of the same scene, protocol and seed, or else one of another seed that started from the
    very same initial views (the FisherRF protocol's farthest-point start does not depend on the seed), so one
    reference per scene serves every seed at the cost of its training noise (~0.1 dB, more on fox)."""
    rows = list(rows)
    refs = [r for r in rows if r.selector == INITIAL and r.psnr_at_round_steps]
    same_seed = {(r.scene, r.protocol, r.seed): r for r in refs}
    same_views = {(r.scene, r.protocol, tuple(r.initial_views)): r
                  for r in sorted(refs, key=lambda r: -r.seed) if r.initial_views}
    out = []
    for r in rows:
        ref = same_seed.get((r.scene, r.protocol, r.seed))
        if ref is None and r.initial_views:
            ref = same_views.get((r.scene, r.protocol, tuple(r.initial_views)))
        if r.is_reference or ref is None or not r.psnr_per_round:
            continue
        at, at_ref = r.psnr_at_round_steps, ref.psnr_at_round_steps
        rounds = [p for p in r.psnr_per_round if p.step in at and p.step in at_ref]
        if not rounds:
            continue
        gains = [at[p.step] - at_ref[p.step] for p in rounds]
        gains.append(r.test.psnr - ref.test.psnr)
        out.append(ViewGain(r, [p.num_views_before for p in rounds], gains))
    return out


def round_gains(rows: Iterable[RunResult]) -> List[Tuple[str, str, int, float]]:
    """(scene, selector, views before the round, what the round's view gained: G(next) - G(this)) of every round
    of runs with a matching `initial` reference (`view_gains`)."""
    return [(v.scene, v.selector, views, v.G[k + 1] - v.G[k])
            for v in view_gains(rows) for k, views in enumerate(v.views)]


def fit_gain_model(rows: Sequence[RunResult], exclude_scene: Optional[str] = None) -> GainModel:
    """Least-squares fit of gain = a + b log(views) per selector and over all, on runs of other scenes."""
    data = [g for g in round_gains(rows) if g[0] != exclude_scene]
    if not data:
        raise ValueError("no rounds to fit on: runs need their test PSNR at every round step (eval-each-round) and an "
                         "`initial` reference of the same scene and protocol (same seed, or the same initial views)")

    def fit(points: List[Tuple[str, str, int, float]]) -> Tuple[float, float]:
        x = np.array([[1.0, math.log(v)] for _, _, v, _ in points])
        y = np.array([g for *_, g in points])
        (a, b), *_ = np.linalg.lstsq(x, y, rcond=None)
        return float(a), float(b)

    coefficients = {ALL: fit(data)}
    for selector in sorted({g[1] for g in data}):
        points = [g for g in data if g[1] == selector]
        if len({v for _, _, v, _ in points}) > 1:
            coefficients[selector] = fit(points)
    return GainModel(coefficients, sorted({g[0] for g in data}))


def stop_round(model: GainModel, selector: str, views_per_round: Sequence[int], threshold: float) -> Optional[int]:
    """The first round (index) whose predicted gain is below `threshold`, or None."""
    for k, views in enumerate(views_per_round):
        if model.predict(selector, views) < threshold:
            return k
    return None


def early_stop_curve(rows: Sequence[RunResult], thresholds: Sequence[float]) -> List[Dict[str, float]]:
    """Views saved against PSNR lost over thresholds, each scene judged with a model fitted on the others.

    A run stopped before round k keeps the views it had then; what it loses is estimated as G(end) - G(s_k), the
    gain its later views brought by the end (`view_gains`)."""
    runs = [v for v in view_gains(rows) if not v.run.smoke and not v.run.repeat]
    models = {scene: fit_gain_model(rows, exclude_scene=scene) for scene in sorted({v.scene for v in runs})}
    curve = []
    for threshold in thresholds:
        saved, lost = [], []
        for v in runs:
            k = stop_round(models[v.scene], v.selector, v.views, threshold)
            saved.append(0 if k is None else len(v.views) - k)
            lost.append(0.0 if k is None else v.G[-1] - v.G[k])
        curve.append({"threshold_db": threshold, "views_saved": float(np.mean(saved)) if runs else 0.0,
                      "psnr_lost_db": float(np.mean(lost)) if runs else 0.0, "runs": len(runs)})
    return curve
