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

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, eval_mode

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
    train_batch: int = 8
    """Active views rendered together for H_train (one backward per probe covers the whole batch; the cross-view
    terms of the squared gradient have zero mean). 1 = one view at a time."""
    resolution_scale: float = 0.5
    """Render views at this fraction of the dataset resolution (FisherRF's information is dominated by coarse
    structure; halving the side quarters the cost)."""


@dataclass
class ViewHessian:
    """diag(J^T J) of one view, stored only for the Gaussians inside its frustum."""

    ids: torch.Tensor
    """[M] indices of the Gaussians that can touch the view."""
    h: Dict[str, torch.Tensor]
    """Per parameter tensor, [M, ...] entries of the diagonal for those Gaussians."""


def frustum_ids(model, camera, margin_sigmas: float = 3.0) -> torch.Tensor:
    """Indices of Gaussians whose 3-sigma extent can reach the image (in front of the near plane)."""
    from nerfstudio.models.splatfacto import get_viewmat

    with torch.no_grad():
        viewmat = get_viewmat(camera.camera_to_worlds)[0].to(model.device)
        K = camera.get_intrinsics_matrices()[0].to(model.device)
        W, H = int(camera.width.item()), int(camera.height.item())
        cam = model.means @ viewmat[:3, :3].T + viewmat[:3, 3]
        z = cam[:, 2]
        front = z > 0.01
        zc = z.clamp_min(0.01)
        u = K[0, 0] * cam[:, 0] / zc + K[0, 2]
        v = K[1, 1] * cam[:, 1] / zc + K[1, 2]
        r = margin_sigmas * torch.exp(model.scales).amax(dim=-1) * K[0, 0] / zc
        inside = (u + r > 0) & (u - r < W) & (v + r > 0) & (v - r < H)
        return torch.nonzero(front & inside).squeeze(-1)


def render_subset(model, camera, leaves: Dict[str, torch.Tensor], ids: torch.Tensor) -> torch.Tensor:
    """RGB render [C, H, W, 3] (cameras of one size) of the Gaussians `ids`, differentiable w.r.t. the `leaves` (raw parameters of those
    Gaussians, as splatfacto stores them); the others come from the model, detached."""
    from nerfstudio.models.splatfacto import get_viewmat

    raw = {n: leaves[n] if n in leaves else model.gauss_params[n][ids].detach() for n in model.gauss_params.keys()}
    viewmat = get_viewmat(camera.camera_to_worlds).to(model.device)
    K = camera.get_intrinsics_matrices().to(model.device)
    W, H = int(camera.width.reshape(-1)[0].item()), int(camera.height.reshape(-1)[0].item())
    colors = torch.cat((raw["features_dc"][:, None, :], raw["features_rest"]), dim=1)
    if model.config.sh_degree > 0:
        sh_degree = min(model.step // model.config.sh_degree_interval, model.config.sh_degree)
    else:
        colors, sh_degree = torch.sigmoid(colors).squeeze(1), None
    render, alpha, _ = model._rasterize(
        means=raw["means"], quats=raw["quats"], scales=torch.exp(raw["scales"]),
        opacities=torch.sigmoid(raw["opacities"]).squeeze(-1), colors=colors, viewmats=viewmat, Ks=K,
        width=W, height=H, packed=False, near_plane=0.01, far_plane=1e10, render_mode="RGB",
        sh_degree=sh_degree, sparse_grad=False, absgrad=False, rasterize_mode=model.config.rasterize_mode,
    )
    background = model.background_color.to(model.device)
    return render + (1 - alpha) * background


class FisherSelector:
    """Greedy information-gain selection; each pick joins H_train before the next."""

    def __init__(self, config: FisherSelectorConfig) -> None:
        self.config = config
        if config.probes < 1 or config.train_probe_factor < 1:
            raise SelectionError("--pipeline.datamanager.fisher.probes and train-probe-factor must be >= 1")

    def param_names(self) -> List[str]:
        return list(FISHER_PARAMS) + (["quats"] if self.config.include_rotations else [])

    def view_hessian(self, context: SelectionContext, index: int, probes: int) -> ViewHessian:
        """diag(J^T J) of one view (probe estimate or exact), for the Gaussians in its frustum."""
        model = context.model
        camera = context.cameras[int(index) : int(index) + 1].to(model.device)
        if self.config.resolution_scale != 1.0:
            camera.rescale_output_resolution(self.config.resolution_scale)
        ids = frustum_ids(model, camera)
        names = self.param_names()
        leaves = {n: model.gauss_params[n][ids].detach().requires_grad_(True) for n in names}
        h = {n: torch.zeros_like(t) for n, t in leaves.items()}
        if ids.numel() == 0:
            return ViewHessian(ids, h)
        with torch.enable_grad():
            rgb = render_subset(model, camera, leaves, ids)
        return ViewHessian(ids, self._probe(rgb, leaves, probes, context.generator))

    def _probe(self, rgb: torch.Tensor, leaves: Dict[str, torch.Tensor], probes: int, generator) -> Dict[str, torch.Tensor]:
        """diag(J^T J) of `rgb` w.r.t. `leaves`: exact (one backward per output) or by Rademacher probes."""
        names = list(leaves)
        h = {n: torch.zeros_like(t) for n, t in leaves.items()}
        params = [leaves[n] for n in names]
        if self.config.mode == "exact":
            flat = rgb.reshape(-1)
            for k in range(flat.numel()):
                grads = torch.autograd.grad(flat[k], params, retain_graph=True, allow_unused=True)
                for n, g in zip(names, grads):
                    if g is not None:
                        h[n] += g.detach() ** 2
        else:
            for k in range(probes):
                eps = (torch.randint(0, 2, rgb.shape, generator=generator) * 2 - 1).to(rgb)
                grads = torch.autograd.grad(rgb, params, grad_outputs=eps, retain_graph=k < probes - 1, allow_unused=True)
                for n, g in zip(names, grads):
                    if g is not None:
                        h[n] += g.detach() ** 2
            h = {n: t / probes for n, t in h.items()}
        return h

    def weights(self, h_train: Dict[str, torch.Tensor]) -> Dict[str, torch.Tensor]:
        """1 / (H_train + lambda) per parameter tensor, with lambda's relative floor."""
        out = {}
        for name, h in h_train.items():
            floor = self.config.reg_lambda + self.config.relative_floor * float(h.mean())
            out[name] = 1.0 / (h + floor)
        return out

    @staticmethod
    def score(view: ViewHessian, weights: Dict[str, torch.Tensor]) -> float:
        return float(sum((view.h[n] * weights[n][view.ids]).sum() for n in view.h))

    def select(self, context: SelectionContext) -> Selection:
        train_probes = self.config.probes * self.config.train_probe_factor
        picked: List[int] = []
        scores: Dict[int, float] = {}
        with eval_mode(context.model):
            # Recomputed every round: densification renumbers the Gaussians.
            h_train = self.train_hessian(context, context.active, train_probes)
            for _ in range(context.num_to_pick):
                weights = self.weights(h_train)
                best, best_score, best_view = -1, -math.inf, None
                # One pass over the pool keeps only the running best's Hessian (memory stays O(#params)).
                for c in context.candidates:
                    if c in picked:
                        continue
                    view = self.view_hessian(context, c, self.config.probes)
                    s = self.score(view, weights)
                    if not math.isfinite(s):
                        raise SelectionError(f"fisher score of view {context.image_names[c]} is not finite")
                    if not picked:
                        scores[c] = s
                    if s > best_score:
                        best, best_score, best_view = c, s, view
                picked.append(best)
                # Greedy batch: the pick's information joins the training side before the next pick.
                for name in h_train:
                    h_train[name].index_add_(0, best_view.ids, best_view.h[name])
        return Selection(indices=picked, scores=scores)

    def train_hessian(self, context: SelectionContext, views: Sequence[int], probes: int) -> Dict[str, torch.Tensor]:
        """H_train: the sum of diag(J^T J) over `views`, full size."""
        model = context.model
        total = {n: torch.zeros_like(model.gauss_params[n]) for n in self.param_names()}
        batch = 1 if self.config.mode == "exact" else max(self.config.train_batch, 1)
        if batch == 1:
            for v in views:
                view = self.view_hessian(context, v, probes)
                for name in total:
                    total[name].index_add_(0, view.ids, view.h[name])
            return total
        views = list(views)
        for start in range(0, len(views), batch):
            cameras = context.cameras[torch.tensor(views[start : start + batch], dtype=torch.long)].to(model.device)
            if self.config.resolution_scale != 1.0:
                cameras.rescale_output_resolution(self.config.resolution_scale)
            same_size = bool((cameras.width == cameras.width[0]).all()) and bool((cameras.height == cameras.height[0]).all())
            if not same_size:
                for v in views[start : start + batch]:
                    view = self.view_hessian(context, v, probes)
                    for name in total:
                        total[name].index_add_(0, view.ids, view.h[name])
                continue
            leaves = {n: model.gauss_params[n].detach().requires_grad_(True) for n in self.param_names()}
            ids = torch.arange(model.num_points, device=model.device)
            with torch.enable_grad():
                rgb = render_subset(model, cameras, leaves, ids)
            for name, h in self._probe(rgb, leaves, probes, context.generator).items():
                total[name] += h
        return total
