"""`fisher`: FisherRF (Jiang et al., ECCV 2024) on stock gsplat and on the CPU rasterizer.

The expected information gain of a candidate view is scored with the diagonal Fisher information of the
Gaussian parameters:

    score(c) = sum_i H_c[i] / (H_train[i] + lambda_i),   H_v = diag(J_v^T J_v),

where J_v is the Jacobian of view v's rendered colour (all pixels and channels) with respect to the Gaussian
parameters (means, SH dc and rest, log-scales, opacity logits; rotations optional) and H_train sums over the
active views.

FisherRF obtains per-pixel squared Jacobians from a modified CUDA rasterizer. Stock gsplat only gives
vector-Jacobian products, so `probe` mode uses Rademacher probes: with eps a random +-1 image,
g = J^T eps satisfies E[g * g] = diag(J^T J) exactly. Its variance is large, and 1 / (H_train + 1e-6) turns a
noisy small H_train into a huge weight, so H_train gets `train_probe_factor` times more probes per view (and it
sums over all active views), and lambda_i = reg_lambda + relative_floor * mean(H_train over that parameter
tensor). `exact` mode back-propagates every pixel-channel (only for tiny images: tests check `probe` against it).
H_train is recomputed every round because densification renumbers the Gaussians. Gaussians outside a view's
frustum get zero gradient and cost nothing in the rasterizer's backward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Sequence, Type

import torch
from nerfstudio.configs.base_config import InstantiateConfig

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, eval_mode, render_with_grad

FISHER_PARAMS = ("means", "features_dc", "features_rest", "scales", "opacities")


@dataclass
class FisherSelectorConfig(InstantiateConfig):
    """FisherRF's diagonal-Fisher information gain, computed with Rademacher probes on stock gsplat."""

    _target: Type = field(default_factory=lambda: FisherSelector)
    probes: int = 16
    """Rademacher probes per candidate view (K)."""
    train_probe_factor: int = 4
    """H_train uses this many times more probes per active view (its noise is amplified by the division)."""
    reg_lambda: float = 1e-6
    """Absolute regulariser added to H_train, as in FisherRF."""
    relative_floor: float = 1e-2
    """Plus this fraction of the mean of H_train over each parameter tensor, so noisy tiny entries of H_train
    cannot dominate the score."""
    mode: Literal["probe", "exact"] = "probe"
    """`probe`: K Rademacher vector-Jacobian products per view. `exact`: one backward per pixel and channel."""
    include_rotations: bool = False
    """Also count the quaternions (FisherRF leaves them out)."""
    resolution_scale: float = 0.5
    """Render views at this fraction of the dataset resolution (FisherRF's information is dominated by coarse
    structure; halving the side quarters the cost)."""


class FisherSelector:
    """Greedy information-gain selection; each pick joins H_train before the next."""

    def __init__(self, config: FisherSelectorConfig) -> None:
        self.config = config
        if config.probes < 1 or config.train_probe_factor < 1:
            raise SelectionError("--pipeline.datamanager.fisher.probes and train-probe-factor must be >= 1")

    def param_names(self) -> List[str]:
        return list(FISHER_PARAMS) + (["quats"] if self.config.include_rotations else [])

    def view_hessian(self, context: SelectionContext, index: int, probes: int) -> Dict[str, torch.Tensor]:
        """diag(J^T J) of one view for each parameter tensor (probe estimate or exact)."""
        model = context.model
        params = [model.gauss_params[name] for name in self.param_names()]
        rgb = render_with_grad(model, context.cameras, index, self.config.resolution_scale)
        if self.config.mode == "exact":
            flat = rgb.reshape(-1)
            h = [torch.zeros_like(p) for p in params]
            for k in range(flat.numel()):
                grads = torch.autograd.grad(flat[k], params, retain_graph=True, allow_unused=True)
                for acc, g in zip(h, grads):
                    if g is not None:
                        acc += g.detach() ** 2
        else:
            h = [torch.zeros_like(p) for p in params]
            for k in range(probes):
                eps = torch.randint(0, 2, rgb.shape, generator=context.generator).to(rgb) * 2 - 1
                grads = torch.autograd.grad(rgb, params, grad_outputs=eps, retain_graph=k < probes - 1, allow_unused=True)
                for acc, g in zip(h, grads):
                    if g is not None:
                        acc += g.detach() ** 2
            h = [acc / probes for acc in h]
        return {name: t for name, t in zip(self.param_names(), h)}

    def weights(self, h_train: Dict[str, torch.Tensor]) -> Dict[str, torch.Tensor]:
        """1 / (H_train + lambda) per parameter tensor, with lambda's relative floor."""
        out = {}
        for name, h in h_train.items():
            floor = self.config.reg_lambda + self.config.relative_floor * float(h.mean())
            out[name] = 1.0 / (h + floor)
        return out

    def score(self, h_view: Dict[str, torch.Tensor], weights: Dict[str, torch.Tensor]) -> float:
        return float(sum((h_view[n] * weights[n]).sum() for n in h_view))

    def select(self, context: SelectionContext) -> Selection:
        train_probes = self.config.probes * self.config.train_probe_factor
        picked: List[int] = []
        scores: Dict[int, float] = {}
        with eval_mode(context.model):
            h_train = self._sum(context, context.active, train_probes)
            for _ in range(context.num_to_pick):
                weights = self.weights(h_train)
                best, best_score, best_h = -1, -math.inf, None
                # One pass over the pool keeps only the running best's Hessian (memory stays O(#params)).
                for c in context.candidates:
                    if c in picked:
                        continue
                    h = self.view_hessian(context, c, self.config.probes)
                    s = self.score(h, weights)
                    if not math.isfinite(s):
                        raise SelectionError(f"fisher score of view {context.image_names[c]} is not finite")
                    if not picked:
                        scores[c] = s
                    if s > best_score:
                        best, best_score, best_h = c, s, h
                picked.append(best)
                # Greedy batch: the pick's information joins the training side before the next pick.
                for name in h_train:
                    h_train[name] = h_train[name] + best_h[name]
        return Selection(indices=picked, scores=scores)

    def _sum(self, context: SelectionContext, views: Sequence[int], probes: int) -> Dict[str, torch.Tensor]:
        total: Dict[str, torch.Tensor] = {}
        for v in views:
            for name, h in self.view_hessian(context, v, probes).items():
                total[name] = total[name] + h if name in total else h
        return total
