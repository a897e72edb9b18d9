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

Views are processed `view_batch` at a time through `hpgs_ns.render.pair_render` (on the model's `splat()`): each
(view, Gaussian) pair has its own copy of the parameters, so one backward pass per probe gives every view of the
batch its own gradient, and only the Gaussians whose footprint reaches a view are gathered for it (frustum
culling). H_train is recomputed every
round because densification renumbers the Gaussians. The colour is linear in the SH coefficients, so their
squared gradients come from each pair's colour gradient d as B_k^2 d^2 (`sh_via_color`) rather than from 48
back-propagated numbers per pair and probe; with `linearize` a probe back-propagates through the rasterizer only,
and each pair's projection Jacobian (taken once per batch) carries its gradient on to the raw parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Literal, Sequence, Tuple, Type

import torch
from torch.profiler import record_function

from hpgs_ns.render.pair_render import PairRender, Splat, render_pairs, sh_squared_gradients
from hpgs_ns.render.viewmats import world_to_camera
from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, SelectorConfig

FISHER_PARAMS = ("means", "features_dc", "features_rest", "scales", "opacities")


@dataclass
class FisherSelectorConfig(SelectorConfig):
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
    view_batch: int = 32
    """Views rendered and differentiated together (each with its own copy of its visible Gaussians, so memory
    grows with it; lower it if GPU memory runs out)."""
    sh_via_color: bool = True
    """Get the SH coefficients' squared gradients from each pair's colour gradient (exact: the colour is linear
    in them) instead of back-propagating into all 3 (degree + 1)^2 of them per probe."""
    linearize: bool = True
    """Back-propagate each probe through the rasterizer only and chain on with each pair's projection Jacobian
    (taken once per batch of views): same gradients, the projection's autograd once per batch instead of once per
    probe. Implies `sh-via-color`."""
    drop_hidden: bool = True
    """Leave out (view, Gaussian) pairs composited into no pixel (occluded, or too faint everywhere): exactly
    zero gradient, so the same scores for one extra forward and backward per batch of views."""
    resolution_scale: float = 0.5
    """Render views at this fraction of the dataset resolution (FisherRF's information is dominated by coarse
    structure; halving the side quarters the cost)."""


@dataclass
class ViewBatch:
    """Views of one image size, with their cameras in the rasterizer's form."""

    views: List[int]
    viewmats: torch.Tensor
    """[C, 4, 4] world-to-camera."""
    Ks: torch.Tensor
    """[C, 3, 3] intrinsics at the rendered size."""
    width: int
    height: int


class FisherSelector:
    """Greedy information-gain selection; each pick joins H_train before the next."""

    def __init__(self, config: FisherSelectorConfig) -> None:
        self.config = config
        self.work: Dict[str, float] = {}
        if config.probes < 1 or config.train_probe_factor < 1 or config.view_batch < 1:
            raise SelectionError("--pipeline.selection.fisher.probes, train-probe-factor and view-batch must be >= 1")
        if not config.resolution_scale > 0:
            raise SelectionError("--pipeline.selection.fisher.resolution-scale must be > 0")

    def param_names(self) -> List[str]:
        return list(FISHER_PARAMS) + (["quats"] if self.config.include_rotations else [])

    # ---- batches of views ----------------------------------------------------------------------------------

    def batches(self, context: SelectionContext, views: Sequence[int]) -> Iterator[ViewBatch]:
        """`views` grouped by rendered size, at most `view_batch` per group."""
        device = context.device
        cameras = context.cameras[torch.tensor([int(v) for v in views], dtype=torch.long)]
        if self.config.resolution_scale != 1.0:
            cameras.rescale_output_resolution(self.config.resolution_scale)
        sizes: Dict[Tuple[int, int], List[int]] = {}
        for k in range(len(views)):
            sizes.setdefault((int(cameras.width[k]), int(cameras.height[k])), []).append(k)
        for (W, H), rows in sizes.items():
            for start in range(0, len(rows), self.config.view_batch):
                chunk = torch.tensor(rows[start : start + self.config.view_batch], dtype=torch.long)
                cams = cameras[chunk]
                yield ViewBatch(
                    views=[int(views[k]) for k in chunk],
                    viewmats=world_to_camera(cams.camera_to_worlds.reshape(-1, 3, 4)).to(device),
                    Ks=cams.get_intrinsics_matrices().reshape(-1, 3, 3).to(device),
                    width=W,
                    height=H,
                )

    def render(self, context: SelectionContext, splat: Splat, batch: ViewBatch) -> PairRender:
        with torch.enable_grad():
            pr = render_pairs(
                splat, batch.viewmats, batch.Ks, batch.width, batch.height, self.param_names(),
                sh_via_color=self.config.sh_via_color, drop_hidden=self.config.drop_hidden, linearize=self.config.linearize,
            )
        full = context.cameras[torch.tensor(batch.views, dtype=torch.long)]
        self._count("views_rendered", len(batch.views))
        self._count("pixels_rendered", len(batch.views) * batch.width * batch.height)
        self._count("pixels_full_resolution", int((full.width * full.height).sum()))
        self._count("pairs_in_frustum", pr.pairs_in_frustum)
        self._count("pairs_differentiated", pr.camera_ids.numel())
        self._count("pairs_unculled", len(batch.views) * splat.num_points)
        return pr

    def _count(self, key: str, n: float) -> None:
        self.work[key] = self.work.get(key, 0) + n

    def pair_squares(self, pr: PairRender, probes: int, generator: torch.Generator) -> Dict[str, torch.Tensor]:
        """Each pair's diag(J^T J) for every Fisher parameter, [nnz, ...] like its leaf: the probe mean of the
        squared pair gradients (in `exact` mode the sum over pixel-channels)."""
        sums: Dict[str, torch.Tensor] = {}
        for grad_image, weight, last in self.upstream_gradients(pr, probes, generator):
            with record_function("fisher.probe_backward"):
                grads = pr.gradients(grad_image, retain_graph=not last)
            for name, g in grads.items():
                if name in sums:
                    sums[name].add_(g.square(), alpha=weight)
                else:
                    sums[name] = g.square().mul_(weight)
        if "color" in sums:  # SH coefficients through the colour gradient (pair_render.sh_squared_gradients)
            sums["features_dc"], sums["features_rest"] = sh_squared_gradients(
                pr.sh_bases, sums.pop("color"), pr.leaves["features_rest"].shape[1]
            )
        return {n: sums[n] if n in sums else torch.zeros_like(pr.leaves[n]) for n in self.param_names()}

    def upstream_gradients(self, pr: PairRender, probes: int, generator: torch.Generator) -> Iterator[Tuple[torch.Tensor, float, bool]]:
        """(upstream gradient of the image, weight, whether it is the last) for each probe (or each pixel-channel
        in `exact` mode): the weighted sum of the squared pair gradients over them is each view's diag(J^T J)."""
        if pr.camera_ids.numel() == 0:
            return
        if self.config.mode == "exact":
            n = pr.image[0].numel()
            for k in range(n):
                # Pixel k of every view at once: the pairs keep the views' gradients apart.
                one_hot = torch.zeros_like(pr.image).reshape(pr.image.shape[0], -1)
                one_hot[:, k] = 1.0
                self._count("backward_passes", 1)
                yield one_hot.reshape(pr.image.shape), 1.0, k == n - 1
            return
        for k in range(probes):
            eps = torch.randint(0, 2, pr.image.shape, generator=generator, device=pr.image.device, dtype=torch.int8)
            self._count("backward_passes", 1)
            yield eps.to(pr.image.dtype).mul_(2).sub_(1), 1.0 / probes, k == probes - 1

    # ---- the two quantities ----------------------------------------------------------------------------------

    def diag_hessian(self, context: SelectionContext, splat: Splat, views: Sequence[int], probes: int,
                     generator: torch.Generator) -> Dict[str, torch.Tensor]:
        """sum over `views` of diag(J_v^T J_v), full size (one entry per Gaussian parameter)."""
        total = {n: torch.zeros_like(splat.params[n]) for n in self.param_names()}
        for batch in self.batches(context, views):
            pr = self.render(context, splat, batch)
            for n, sq in self.pair_squares(pr, probes, generator).items():
                total[n].index_add_(0, pr.gaussian_ids, sq)
        return total

    def view_scores(self, context: SelectionContext, splat: Splat, views: Sequence[int], weights: Dict[str, torch.Tensor],
                    generator: torch.Generator) -> Dict[int, float]:
        """score(v) = sum_i diag(J_v^T J_v)[i] * weights[i] for each of `views`."""
        scores: Dict[int, float] = {}
        for batch in self.batches(context, views):
            pr = self.render(context, splat, batch)
            gids = pr.gaussian_ids
            per_pair = torch.zeros(gids.shape[0], dtype=pr.image.dtype, device=pr.image.device)
            for n, sq in self.pair_squares(pr, self.config.probes, generator).items():
                per_pair += (sq * weights[n][gids]).flatten(1).sum(1)
            per_view = torch.zeros(len(batch.views), dtype=torch.float64, device=per_pair.device)
            per_view.index_add_(0, pr.camera_ids, per_pair.double())
            scores.update({v: float(s) for v, s in zip(batch.views, per_view.tolist())})
        return scores

    def weights(self, h_train: Dict[str, torch.Tensor]) -> Dict[str, torch.Tensor]:
        """1 / (H_train + lambda) per parameter tensor, with lambda's relative floor."""
        out = {}
        for name, h in h_train.items():
            floor = self.config.reg_lambda + self.config.relative_floor * float(h.mean())
            out[name] = 1.0 / (h + floor)
        return out

    # ---- selection -------------------------------------------------------------------------------------------

    def select(self, context: SelectionContext) -> Selection:
        model = context.model
        # Probes are drawn on the model's device (a CPU generator would ship every probe image to the GPU),
        # seeded from the round's generator so a resumed run makes the same choices.
        generator = torch.Generator(device=context.device)
        generator.manual_seed(int(torch.randint(0, 2**62, (1,), generator=context.generator)))
        picked: List[int] = []
        first_scores: Dict[int, float] = {}
        self.work = {}
        train_probes = self.config.probes * self.config.train_probe_factor
        with model.eval_mode():
            splat = model.splat()
            # Recomputed every round: densification renumbers the Gaussians.
            h_train = self.diag_hessian(context, splat, context.active, train_probes, generator)
            for _ in range(context.num_to_pick):
                pool = [c for c in context.candidates if c not in picked]
                scores = self.view_scores(context, splat, pool, self.weights(h_train), generator)
                bad = [context.image_names[c] for c, s in scores.items() if not math.isfinite(s)]
                if bad:
                    raise SelectionError(f"fisher score of view {bad[0]} is not finite (the splat has NaN parameters?)")
                best = max(pool, key=lambda c: scores[c])
                if not picked:
                    first_scores = scores
                picked.append(best)
                if len(picked) < context.num_to_pick:
                    # Greedy batch: the pick's information joins the training side before the next pick.
                    h_pick = self.diag_hessian(context, splat, [best], train_probes, generator)
                    for name in h_train:
                        h_train[name] += h_pick[name]
        return Selection(indices=picked, scores=first_scores, work=dict(self.work))

