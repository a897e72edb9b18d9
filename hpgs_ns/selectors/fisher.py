"""`fisher`: FisherRF (Jiang et al., ECCV 2024) and POp-GS's D-optimal criteria, on stock gsplat and the CPU rasterizer.

The information a candidate view adds is measured with the Fisher information J_v^T J_v of the Gaussian
parameters, where J_v is the Jacobian of view v's rendered colour (all pixels and channels) with respect to the
Gaussian parameters (means, SH dc and rest, log-scales, opacity logits; rotations optional); H_train sums over
the active views. `criterion` picks the score:

    trace:       score(c) = sum_i H_c[i] / (H_train[i] + lambda_i),           H_v = diag(J_v^T J_v)   (FisherRF)
    dopt:        score(c) = sum_i log(1 + H_c[i] / (H_train[i] + lambda_i))                            (POp-GS)
               = logdet(H_train + Lambda + H_c) - logdet(H_train + Lambda) for the diagonal matrices
    dopt-block:  score(c) = sum_g [logdet(A_g + B_{c,g}) - logdet(A_g)],      A_g = H_train,g + diag(lambda)

POp-GS (CVPR 2025) scores views by D-optimality. In `dopt-block` each Gaussian g has a full block of J^T J over
`block_names()`: means (3), SH dc or RGB logits (3), log-scales (3), opacity logit (1) and, with
`include_rotations`, the quaternion (4), laid out in that order (10 or 14 rows); the SH rest (3 per coefficient)
stays diagonal, i.e. its own entries of J^T J, without its cross terms (a full block would be 55 or 59 rows at
degree 3). So B_{c,g} is the block of pair (c, g) plus diag(SH rest), and the rest adds `dopt`'s terms.

FisherRF obtains per-pixel squared Jacobians from a modified CUDA rasterizer. Stock gsplat only gives
vector-Jacobian products, so `probe` mode uses Rademacher probes: with eps a random +-1 image, g = J^T eps
satisfies E[g * g] = diag(J^T J) and E[g g^T] = J^T J exactly (the blocks are probe means of each pair's gradient
outer product). Its variance is large, and 1 / (H_train + 1e-6) turns a noisy small H_train into a huge weight, so
H_train gets `train_probe_factor` times more probes per view (and it sums over all active views), and lambda_i =
reg_lambda + relative_floor * mean(diag H_train over that parameter tensor). `exact` mode back-propagates every
pixel-channel (only for tiny images: tests check `probe` against it).

Several views a round are picked greedily: each pick's Hessian (diagonal or blocks) joins H_train before the next
pick is scored. Under `dopt`/`dopt-block` lambda stays the round's, so each pick is the marginal log-det gain of one
monotone submodular set function (so the greedy set's gain is at least (1 - 1/e) of the best set's); under `trace`
the floor follows H_train, as it always has.

Views are processed `view_batch` at a time through `hpgs_ns.render.pair_render` (on the model's `splat()`): each
(view, Gaussian) pair has its own copy of the parameters, so one backward pass per probe gives every view of the
batch its own gradient, and only the Gaussians whose footprint reaches a view are gathered for it (frustum
culling). H_train is recomputed every
round because densification renumbers the Gaussians. The colour is linear in the SH coefficients, so their
gradients come from each pair's colour gradient d as B_k d (`sh_via_color`) rather than from 48 back-propagated
numbers per pair and probe: the squares are B_k^2 d^2, and a block's dc entries come from B_0 d (B_0 a constant).
With `linearize` a probe back-propagates through the rasterizer only, and each pair's projection Jacobian (taken
once per batch) carries its gradient on to the raw parameters. Both are exact for every criterion.

The maths takes plain tensors (`trace_gain`, `dopt_gain`, `block_logdet_gain`, and `greedy_joint` for explicit
per-view Hessians): the selector applies the gains to each (view, Gaussian) pair and picks with `greedy`, as
`greedy_joint` does, re-rendering each pick rather than holding every candidate's Hessian.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterator, List, Literal, Sequence, Tuple, Type, Union

import torch
import tyro
from torch import Tensor
from torch.profiler import record_function
from typing_extensions import Annotated

from hpgs_ns.errors import check_option
from hpgs_ns.render.pair_render import PairRender, Splat, render_pairs, sh_squared_gradients
from hpgs_ns.render.viewmats import ViewBatch, view_batches
from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, SelectorConfig

FISHER_PARAMS = ("means", "features_dc", "features_rest", "scales", "opacities")
BLOCK_PARAMS = ("means", "features_dc", "scales", "opacities")  # `dopt-block`'s full block (+ quats); the SH rest: diagonal
BLOCK_WIDTHS = {"means": 3, "features_dc": 3, "scales": 3, "opacities": 1, "quats": 4}
CRITERIA = ("trace", "dopt", "dopt-block")
# A string, not a Literal: tyro would draw its own error box for an unknown value; `__post_init__` says it in one line.
CriterionName = Annotated[str, tyro.conf.arg(metavar="{" + ",".join(CRITERIA) + "}")]
Lambda = Union[float, Tensor]


# ---- the criteria on plain tensors ---------------------------------------------------------------------------


def _row_sums(x: Tensor) -> Tensor:
    """[M, ...] -> [M]: the sum over everything but the first dim."""
    return x.flatten(1).sum(1) if x.dim() > 1 else x


def trace_gain(h_c: Tensor, h_train: Tensor, lam: Lambda) -> Tensor:
    """FisherRF's score: sum_i h_c[i] / (h_train[i] + lam_i) for each of M candidates.

    h_c [M, ...] the candidates' diagonal Hessians, h_train broadcastable to h_c, lam a float or a tensor
    broadcastable to h_c -> [M]."""
    return _row_sums(h_c * (1.0 / (h_train + lam)))


def dopt_gain(h_c: Tensor, h_train: Tensor, lam: Lambda) -> Tensor:
    """POp-GS's D-optimal gain of diagonal Hessians: sum_i log(1 + h_c[i] / (h_train[i] + lam_i)), which is
    logdet(diag(h_train + lam + h_c)) - logdet(diag(h_train + lam)). Shapes as `trace_gain`."""
    return _row_sums(torch.log1p(h_c / (h_train + lam)))


def block_logdet_gain(b_c: Tensor, h_train: Tensor, lam: Tensor) -> Tensor:
    """POp-GS's per-block D-optimal gain: sum over blocks of logdet(A + B) - logdet(A), with A = h_train + diag(lam).

    b_c [M, ..., p, p] the candidates' blocks (symmetric PSD), h_train [..., p, p] broadcastable to b_c (PSD), lam
    [p] (positive) -> [M]. Computed as logdet(I + L^-1 B L^-T) with A = L L^T (no cancellation between two large
    log-dets), after scaling A and B by diag(A)^-1/2 on both sides (same ratio, better conditioned in float32).
    A block whose Cholesky fails (A not positive definite) gives NaN."""
    a = h_train + torch.diag_embed(lam)
    s = a.diagonal(dim1=-2, dim2=-1).rsqrt()
    scale = s[..., :, None] * s[..., None, :]
    chol, bad = torch.linalg.cholesky_ex(a * scale)
    x = torch.linalg.solve_triangular(chol, b_c * scale, upper=False)  # L^-1 B
    m = torch.linalg.solve_triangular(chol, x.transpose(-1, -2), upper=False)  # L^-1 B L^-T
    eye = torch.eye(b_c.shape[-1], dtype=b_c.dtype, device=b_c.device)
    chol_m, bad_m = torch.linalg.cholesky_ex(eye + 0.5 * (m + m.transpose(-1, -2)))
    gain = 2 * chol_m.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    gain = torch.where((bad == 0) & (bad_m == 0), gain, torch.nan)
    return _row_sums(gain)


def greedy(score: Callable[[List[int]], Dict[int, float]], add: Callable[[int], None], pool: Sequence[int],
           k: int) -> Tuple[List[int], Dict[int, float]]:
    """Pick k of `pool` one at a time: `score(rest)` scores the views not picked yet ({view: score}), the best
    (first on ties) is picked, and `add(view)` makes its information count before the next is scored.
    Returns (the picks in order, the first scores)."""
    picked: List[int] = []
    first: Dict[int, float] = {}
    for _ in range(k):
        rest = [c for c in pool if c not in picked]
        scores = score(rest)
        best = max(rest, key=lambda c: scores[c])
        if not picked:
            first = scores
        picked.append(best)
        if len(picked) < k:
            add(best)
    return picked, first


def greedy_joint(gain_fn: Callable[[Tensor, Tensor], Tensor], per_view_hessians: Tensor, h_train: Tensor,
                 k: int) -> Tuple[List[int], Tensor]:
    """The greedy joint choice of k views: each pick's Hessian joins h_train before the next pick.

    gain_fn(h_c [M, *S], h_train [*S]) -> [M] (e.g. `dopt_gain` with its lam bound), per_view_hessians [V, *S]
    (diagonals [V, P] or blocks [V, G, p, p]), h_train [*S]. Returns (the k picks in order, the first pick's
    gains [V] of every view). With `dopt_gain`/`block_logdet_gain` each pick maximises the marginal log-det gain."""
    h = h_train.clone()
    views = list(range(per_view_hessians.shape[0]))

    def score(rest: List[int]) -> Dict[int, float]:
        return dict(zip(rest, gain_fn(per_view_hessians[rest], h).tolist()))

    picked, first = greedy(score, lambda v: h.add_(per_view_hessians[v]), views, min(k, len(views)))
    return picked, torch.tensor([first[v] for v in views], dtype=torch.float64)


@dataclass
class FisherSelectorConfig(SelectorConfig):
    """The information a candidate adds by the Fisher information of the Gaussians (FisherRF's trace, or POp-GS's
    D-optimal log-det gains), computed with Rademacher probes on stock gsplat."""

    _target: Type = field(default_factory=lambda: FisherSelector)
    criterion: CriterionName = "trace"
    """How a candidate's Fisher information is scored against the training views'. `trace`: FisherRF's
    sum_i H_c[i] / (H_train[i] + lambda_i) over the diagonals. `dopt`: POp-GS's D-optimal gain
    sum_i log(1 + H_c[i] / (H_train[i] + lambda_i)) over the same diagonals. `dopt-block`: POp-GS's log-det gain over
    each Gaussian's full block of means, SH dc, log-scales, opacity (and rotation with include-rotations), the SH
    rest diagonal; an outer product per pair and probe and a Cholesky per pair. Several views a round: greedy, each
    pick's Hessian joins H_train before the next."""
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

    def __post_init__(self) -> None:
        # tyro builds this config while it parses the command line: an unknown criterion is one line, not its box.
        self.check_criterion()

    def check_criterion(self) -> None:
        check_option("--pipeline.selection.fisher.criterion", self.criterion, self.criterion in CRITERIA,
                     "unknown criterion", "choose trace, dopt or dopt-block")



class FisherSelector:
    """Greedy information-gain selection; each pick joins H_train before the next."""

    def __init__(self, config: FisherSelectorConfig) -> None:
        self.config = config
        self.work: Dict[str, float] = {}
        config.check_criterion()  # also when set after the config was built
        if config.probes < 1 or config.train_probe_factor < 1 or config.view_batch < 1:
            raise SelectionError("--pipeline.selection.fisher.probes, train-probe-factor and view-batch must be >= 1")
        if not config.resolution_scale > 0:
            raise SelectionError("--pipeline.selection.fisher.resolution-scale must be > 0")

    def param_names(self) -> List[str]:
        return list(FISHER_PARAMS) + (["quats"] if self.config.include_rotations else [])

    def block_names(self) -> List[str]:
        """`dopt-block`'s block rows, in order (BLOCK_WIDTHS each): means, features_dc, scales, opacities[, quats]."""
        return list(BLOCK_PARAMS) + (["quats"] if self.config.include_rotations else [])

    # ---- batches of views ----------------------------------------------------------------------------------

    def batches(self, context: SelectionContext, views: Sequence[int]) -> Iterator[ViewBatch]:
        """`views` grouped by rendered size, at most `view_batch` per group."""
        return view_batches(context.cameras, views, self.config.resolution_scale, self.config.view_batch, context.device)

    def render(self, context: SelectionContext, splat: Splat, batch: ViewBatch) -> PairRender:
        with torch.enable_grad():
            pr = render_pairs(
                splat, batch.viewmats, batch.Ks, batch.width, batch.height, self.param_names(),
                sh_via_color=self.config.sh_via_color, drop_hidden=self.config.drop_hidden, linearize=self.config.linearize,
            )
        full = context.cameras[torch.tensor(batch.views, dtype=torch.long)]
        context.progress(len(batch.views))
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

    def pair_blocks(self, pr: PairRender, probes: int, generator: torch.Generator) -> Dict[str, torch.Tensor]:
        """`dopt-block`'s per-pair Hessian: "block" [nnz, p, p], each pair's J^T J over `block_names()` (the probe
        mean of its gradient outer products; in `exact` mode the sum over pixel-channels), and "features_rest"
        [nnz, n_rest, 3], the diagonal of its SH rest. With the SH through the colour gradient d, the dc gradient
        is B_0 d (exact: the colour is linear in the coefficients, B_0 a constant) and the rest's squares
        B_k^2 d^2."""
        names = self.block_names()
        rows = pr.camera_ids.numel()
        like = pr.leaves["means"]
        block = like.new_zeros(rows, sum(BLOCK_WIDTHS[n] for n in names), sum(BLOCK_WIDTHS[n] for n in names))
        rest_sq = torch.zeros_like(pr.leaves["features_rest"])
        color_sq = None
        for grad_image, weight, last in self.upstream_gradients(pr, probes, generator):
            with record_function("fisher.probe_backward"):
                grads = pr.gradients(grad_image, retain_graph=not last)
            if "color" in grads:
                d = grads.pop("color")
                grads["features_dc"] = pr.sh_bases[:, :1] * d
                color_sq = d.square().mul_(weight) if color_sq is None else color_sq.add_(d.square(), alpha=weight)
            elif "features_rest" in grads:
                rest_sq.add_(grads["features_rest"].square(), alpha=weight)
            u = torch.cat([grads[n].reshape(rows, -1) if n in grads else like.new_zeros(rows, BLOCK_WIDTHS[n])
                           for n in names], 1)
            block.addcmul_(u[:, :, None], u[:, None, :], value=weight)
        if color_sq is not None:
            rest_sq = sh_squared_gradients(pr.sh_bases, color_sq, rest_sq.shape[1])[1]
        return {"block": block, "features_rest": rest_sq}

    def pair_hessians(self, pr: PairRender, probes: int, generator: torch.Generator) -> Dict[str, torch.Tensor]:
        """Each pair's Hessian in the criterion's form: `pair_blocks` for `dopt-block`, else `pair_squares`."""
        if self.config.criterion == "dopt-block":
            return self.pair_blocks(pr, probes, generator)
        return self.pair_squares(pr, probes, generator)

    # ---- the two quantities ----------------------------------------------------------------------------------

    def hessian(self, context: SelectionContext, splat: Splat, views: Sequence[int], probes: int,
                generator: torch.Generator) -> Dict[str, torch.Tensor]:
        """Sum over `views` of each view's Hessian, full size: diag(J_v^T J_v) per parameter tensor ([N, ...] like
        it) or, for `dopt-block`, "block" [N, p, p] and "features_rest" [N, n_rest, 3]."""
        params = splat.params
        if self.config.criterion == "dopt-block":
            p = sum(BLOCK_WIDTHS[n] for n in self.block_names())
            total = {"block": params["means"].new_zeros(splat.num_points, p, p),
                     "features_rest": torch.zeros_like(params["features_rest"])}
        else:
            total = {n: torch.zeros_like(params[n]) for n in self.param_names()}
        for batch in self.batches(context, views):
            pr = self.render(context, splat, batch)
            for n, h in self.pair_hessians(pr, probes, generator).items():
                total[n].index_add_(0, pr.gaussian_ids, h)
        return total

    def lambdas(self, h_train: Dict[str, torch.Tensor]) -> Dict[str, Lambda]:
        """lambda per entry of `hessian`'s dict: reg_lambda + relative_floor * the mean of H_train's diagonal over
        each parameter tensor (a float; for "block" a [p] tensor, each row its parameter tensor's)."""
        def floor(diag: torch.Tensor) -> float:
            return self.config.reg_lambda + self.config.relative_floor * float(diag.mean())

        if "block" not in h_train:
            return {name: floor(h) for name, h in h_train.items()}
        diag, parts, start = h_train["block"].diagonal(dim1=-2, dim2=-1), [], 0
        for name in self.block_names():
            width = BLOCK_WIDTHS[name]
            parts.append(diag.new_full((width,), floor(diag[:, start : start + width])))
            start += width
        return {"block": torch.cat(parts), "features_rest": floor(h_train["features_rest"])}

    def pair_gains(self, pr: PairRender, h_train: Dict[str, torch.Tensor], lam: Dict[str, Lambda],
                   generator: torch.Generator) -> torch.Tensor:
        """[nnz] each pair's part of its view's score (a view's pairs are distinct Gaussians, and every criterion
        is a sum over Gaussians)."""
        gids = pr.gaussian_ids
        per_pair = torch.zeros(gids.shape[0], dtype=pr.image.dtype, device=pr.image.device)
        diagonal_gain = trace_gain if self.config.criterion == "trace" else dopt_gain
        for name, h in self.pair_hessians(pr, self.config.probes, generator).items():
            gain = block_logdet_gain if name == "block" else diagonal_gain
            with record_function("fisher.gain"):
                per_pair += gain(h, h_train[name][gids], lam[name])
        return per_pair

    def view_scores(self, context: SelectionContext, splat: Splat, views: Sequence[int],
                    h_train: Dict[str, torch.Tensor], lam: Dict[str, Lambda], generator: torch.Generator) -> Dict[int, float]:
        """The criterion's score of each of `views` against `h_train` (as `hessian` returns) and `lam` (as
        `lambdas` returns)."""
        scores: Dict[int, float] = {}
        for batch in self.batches(context, views):
            pr = self.render(context, splat, batch)
            per_pair = self.pair_gains(pr, h_train, lam, generator)
            per_view = torch.zeros(len(batch.views), dtype=torch.float64, device=per_pair.device)
            per_view.index_add_(0, pr.camera_ids, per_pair.double())
            scores.update({v: float(s) for v, s in zip(batch.views, per_view.tolist())})
        return scores

    # ---- selection -------------------------------------------------------------------------------------------

    def select(self, context: SelectionContext) -> Selection:
        model = context.model
        # Probes are drawn on the model's device (a CPU generator would ship every probe image to the GPU),
        # seeded from the round's generator so a resumed run makes the same choices.
        generator = torch.Generator(device=context.device)
        generator.manual_seed(int(torch.randint(0, 2**62, (1,), generator=context.generator)))
        self.work = {}
        train_probes = self.config.probes * self.config.train_probe_factor
        with model.eval_mode():
            splat = model.splat()
            # Recomputed every round: densification renumbers the Gaussians.
            h_train = self.hessian(context, splat, context.active, train_probes, generator)
            # D-optimal: one lambda for the round, so the greedy maximises one log-det set function. trace: the
            # floor follows H_train (FisherRF's weights).
            round_lam = None if self.config.criterion == "trace" else self.lambdas(h_train)

            def score(pool: List[int]) -> Dict[int, float]:
                lam = self.lambdas(h_train) if round_lam is None else round_lam
                scores = self.view_scores(context, splat, pool, h_train, lam, generator)
                bad = [context.image_names[c] for c, s in scores.items() if not math.isfinite(s)]
                if bad:
                    raise SelectionError(f"fisher score of view {bad[0]} is not finite (the splat has NaN parameters?)")
                return scores

            def add(best: int) -> None:
                # Greedy batch: the pick's information joins the training side before the next pick.
                h_pick = self.hessian(context, splat, [best], train_probes, generator)
                for name in h_train:
                    h_train[name] += h_pick[name]

            picked, first_scores = greedy(score, add, context.candidates, context.num_to_pick)
        return Selection(indices=picked, scores=first_scores, work=dict(self.work))
