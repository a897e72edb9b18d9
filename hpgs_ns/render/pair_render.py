"""Render several views so that every (view, Gaussian) pair owns its own copy of the Gaussian's parameters.

A normal render shares the Gaussians between the cameras of a batch, so one backward pass returns the *sum* of
the views' gradients. FisherRF needs each view's own squared gradient; with gsplat's `rasterization` that meant
one backward per view and probe (200 candidates x 16 probes = 3200 launch-bound passes, 7.6 s on an H200).

Here the pairs whose footprint reaches a view are found first (no autograd: this is the frustum culling, so a
view costs only its visible Gaussians), their raw parameters are gathered into leaf tensors [nnz, ...], projected
in PyTorch (`cpu_raster.project`: gsplat's EWA maths, with the settings and activations of the model's own renders,
`render.rasterize`), and composited by gsplat's packed `rasterize_to_pixels` (CUDA) or its pure-PyTorch twin
`cpu_raster.rasterize_pairs`. The splat comes in as plain tensors (`Splat`, from `HpgsSplatfactoModel.splat()`), as
gsplat's functions take them. One backward pass then gives every pair's gradient: every view's own gradient, for a
whole batch of views at once.

With `linearize` the probes stop at the rasterizer: each pair's projected inputs (means2d, conics, opacity,
colour) become the leaves, the Jacobian of those 9 numbers w.r.t. the pair's raw parameters is taken once per
batch (batched backward passes: 6 rows through the projection, 3 through the SH colour), and each probe's
gradient is the rasterizer's backward followed by one [9 x P] product per pair. The projection's autograd was about
two thirds of a Fisher round's GPU time when it ran once per probe (profiled on an H100).

No library offers per-view gradients of a batched render (gsplat's batched API shares the 3D parameters), which
is why this is written here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor
from torch.profiler import record_function  # named ranges, so a torch profile shows where a Fisher round's time goes

from hpgs_ns.cpu_raster import project, quat_scale_to_covar, rasterize_pairs, sh_bases, sh_to_color
from hpgs_ns.render.rasterize import EPS2D, FAR_PLANE, NEAR_PLANE, TILE_SIZE, splat_colors, splat_opacities

SH_PARAMS = ("features_dc", "features_rest")
PAIRS_PER_CHUNK = 1 << 22  # (camera, Gaussian) pairs tested at once when culling (bounds memory, not results)
JACOBIAN_PAIRS_PER_CHUNK = 1 << 20  # pairs whose projection Jacobian is taken at once (6 batched copies of its graph)
RASTER_INPUTS = (("means2d", 2), ("conics", 3), ("opacities", 1), ("colors", 3))  # what the rasterizer reads per pair


@dataclass
class Splat:
    """What a pair render needs of a splat: its Gaussians as splatfacto stores them, and how splatfacto renders them."""

    params: Dict[str, Tensor]
    """Raw, detached: means [N, 3], quats [N, 4], scales [N, 3] (log), opacities [N, 1] (logit), features_dc
    [N, 3] and features_rest [N, K, 3] (SH coefficients, or sigmoid RGB logits in features_dc when sh_degree is
    None)."""
    sh_degree: Optional[int]
    """The SH degree rendered with at the current step (None: plain RGB colours)."""
    background: Tensor
    """[3] background colour."""
    antialiased: bool = False
    """gsplat's `rasterize_mode="antialiased"` (opacity times the low-pass compensation)."""
    backend: str = "cpu"
    """`gsplat` (CUDA kernels) or `cpu` (`cpu_raster`)."""

    @property
    def num_points(self) -> int:
        return int(self.params["means"].shape[0])


@dataclass
class PairRender:
    """A batch of RGB renders whose graph keeps each (view, Gaussian) pair's parameters separate."""

    image: Tensor
    """[C, H, W, 3] RGB composited over the model's background (not clamped)."""
    leaves: Dict[str, Tensor]
    """Raw parameters (as splatfacto stores them) of every pair, [nnz, ...]; those asked for require grad."""
    camera_ids: Tensor
    """[nnz] which view of the batch each pair belongs to."""
    gaussian_ids: Tensor
    """[nnz] which Gaussian of the model each pair copies."""
    color_offset: Tensor | None = None
    """[nnz, 3] zeros added to each pair's SH colour (before the +0.5 and clamp), requiring grad: its gradient is
    the colour gradient d that gives the SH coefficients' gradients as B_k * d (`render_pairs(sh_via_color=True)`)."""
    sh_bases: Tensor | None = None
    """[nnz, (degree+1)^2] the SH bases B_k at each pair's viewing direction (detached), with `color_offset`."""
    pairs_in_frustum: int = 0
    """Pairs whose footprint reaches a view, before `drop_hidden` left out those composited nowhere."""
    raster_inputs: List[Tensor] | None = None
    """`linearize`: the rasterizer's per-pair inputs (RASTER_INPUTS), leaves of `image`'s graph."""
    jacobian: Tensor | None = None
    """`linearize`: [nnz, 9, P] d(raster inputs) / d(the pair's raw parameters `jacobian_params`, flattened)."""
    jacobian_params: List[str] = field(default_factory=list)
    """`linearize`: the parameters laid out along the Jacobian's last dim, in order."""
    color_mask: Tensor | None = None
    """`linearize` with SH: [nnz, 3] whether each colour channel is above the clamp at 0 (else its gradient is 0)."""

    def gradients(self, grad_image: Tensor, retain_graph: bool = True) -> Dict[str, Tensor]:
        """Each pair's gradient of <grad_image, image> w.r.t. its differentiated parameters (by name, [nnz, ...]
        like its leaf) and, where the SH coefficients go through the colour, "color" ([nnz, 3], before the clamp)."""
        if self.jacobian is None:
            names = [n for n, t in self.leaves.items() if t.requires_grad]
            inputs = [self.leaves[n] for n in names] + ([self.color_offset] if self.color_offset is not None else [])
            grads = torch.autograd.grad(self.image, inputs, grad_image, retain_graph=retain_graph, allow_unused=True)
            grads = [torch.zeros_like(t) if g is None else g for t, g in zip(inputs, grads, strict=True)]
            return dict(zip(names + (["color"] if self.color_offset is not None else []), grads, strict=True))
        grads = torch.autograd.grad(self.image, self.raster_inputs, grad_image, retain_graph=retain_graph,
                                    allow_unused=True)
        g_raster = torch.cat(
            [torch.zeros_like(t) if g is None else g for t, g in zip(self.raster_inputs, grads, strict=True)], 1
        )
        flat = (g_raster[:, :, None] * self.jacobian).sum(1)  # [nnz, P]: chain rule through the projection
        out, start = {}, 0
        for name in self.jacobian_params:
            shape = self.leaves[name].shape
            width = shape[1:].numel()
            out[name] = flat[:, start : start + width].reshape(shape)
            start += width
        if self.color_mask is not None:
            out["color"] = g_raster[:, -3:] * self.color_mask
        return out


@torch.no_grad()
def visible_pairs(means: Tensor, covars: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int):
    """(camera_ids, gaussian_ids, radii) of the pairs gsplat would rasterize: in front of the near plane, a
    positive-definite 2D covariance, and a 3-sigma footprint that reaches the image. Non-finite Gaussians are left
    out. means [N, 3], covars [N, 3, 3], viewmats [C, 4, 4], Ks [C, 3, 3]."""
    N, C = means.shape[0], viewmats.shape[0]
    ok = torch.isfinite(means).all(-1) & torch.isfinite(covars).flatten(1).all(-1)
    means = torch.where(ok[:, None], means, 0.0)
    covars = torch.where(ok[:, None, None], covars, 0.0)
    cams_per_chunk = max(1, PAIRS_PER_CHUNK // max(N, 1))
    cids, gids, radii = [], [], []
    for start in range(0, C, cams_per_chunk):
        vm, K = viewmats[start : start + cams_per_chunk], Ks[start : start + cams_per_chunk]
        proj = project(means[None], covars[None], vm[:, None], K[:, None], width, height, EPS2D, False,
                       radius_floor=0.1)  # gsplat's packed kernel's floor
        m2, r = proj["means2d"], proj["radius"]
        depths = proj["depths"]
        valid = ok[None] & (depths >= NEAR_PLANE) & (depths <= FAR_PLANE)
        valid &= (proj["det"] > 0) & (r > 0) & torch.isfinite(r)
        valid &= torch.isfinite(m2).all(-1) & torch.isfinite(proj["conics"]).all(-1)
        valid &= (m2[..., 0] + r > 0) & (m2[..., 0] - r < width) & (m2[..., 1] + r > 0) & (m2[..., 1] - r < height)
        c, g = torch.nonzero(valid, as_tuple=True)
        cids.append(c + start)
        gids.append(g)
        radii.append(r[c, g].int())
    return torch.cat(cids), torch.cat(gids), torch.cat(radii)


def render_pairs(
    splat: Splat, viewmats: Tensor, Ks: Tensor, width: int, height: int, grad_params: Sequence[str],
    sh_via_color: bool = False, drop_hidden: bool = False, linearize: bool = False,
) -> PairRender:
    """Eval-mode RGB of C views of one size ([C, 4, 4] world-to-camera, [C, 3, 3] intrinsics), differentiable
    w.r.t. each pair's copy of `grad_params` (names of `splat.params`), with `splat.backend`'s rasterizer.

    `sh_via_color`: the SH coefficients (`features_dc`, `features_rest`) get no gradient of their own; the
    render carries `color_offset` and `sh_bases` instead, from which `sh_squared_gradients` gives theirs. The
    colour is linear in the coefficients, so this is exact, and a backward pass then writes 3 numbers per pair
    for them instead of 3 (degree + 1)^2.

    `drop_hidden`: leave out the pairs the rasterizer composites into no pixel (behind opaque surfaces, or alpha
    below 1/255 everywhere). They change no pixel and get exactly zero gradient, so the image and every kept
    pair's gradient are the same; finding them costs one forward and backward without parameter gradients.

    `linearize`: `image` is differentiable w.r.t. `raster_inputs` only, and `PairRender.gradients` carries the
    gradient on to the parameters with each pair's projection Jacobian (the SH coefficients through the colour,
    as with `sh_via_color`). Same gradients; each probe then back-propagates through the rasterizer alone."""
    params = {n: t.detach() for n, t in splat.params.items()}
    C = viewmats.shape[0]
    with torch.no_grad():
        covars = quat_scale_to_covar(params["quats"], torch.exp(params["scales"]))
    with record_function("pair_render.cull"):
        cids, gids, radii = visible_pairs(params["means"], covars, viewmats, Ks, width, height)
    in_frustum = int(cids.numel())
    rasterize = _rasterize_gsplat if splat.backend == "gsplat" else _rasterize_cpu
    backgrounds = splat.background.to(viewmats).expand(C, 3).contiguous()
    if drop_hidden and in_frustum:
        with record_function("pair_render.drop_hidden"):
            keep = composited(splat, params, cids, gids, radii, viewmats, Ks, width, height, rasterize, backgrounds)
        cids, gids, radii = cids[keep], gids[keep], radii[keep]
    degree = splat.sh_degree
    via_color = (sh_via_color or linearize) and degree is not None
    if via_color:
        grad_params = [n for n in grad_params if n not in SH_PARAMS]
    if linearize:
        return _render_linearized(splat, params, cids, gids, radii, viewmats, Ks, width, height, grad_params,
                                  rasterize, backgrounds, in_frustum)
    leaves = {n: t[gids].requires_grad_(n in grad_params) for n, t in params.items()}

    proj, opacities = project_pairs(splat, leaves, cids, viewmats, Ks, width, height)
    offset = bases = None
    colors = pair_colors(leaves, cids, viewmats, degree)
    if via_color:
        offset = torch.zeros_like(colors, requires_grad=True)
        colors = colors + offset
        bases = pair_sh_bases(leaves, cids, viewmats, degree)
    if degree is not None:
        colors = torch.clamp_min(colors, 0.0)
    image, _ = rasterize(proj["means2d"], proj["conics"], colors, opacities, radii, proj["depths"], cids, gids, C,
                         width, height, backgrounds)
    return PairRender(
        image=image, leaves=leaves, camera_ids=cids, gaussian_ids=gids, color_offset=offset, sh_bases=bases,
        pairs_in_frustum=in_frustum,
    )


def pair_colors(p: Dict[str, Tensor], cids: Tensor, viewmats: Tensor, degree: int | None) -> Tensor:
    """splatfacto's colour of each pair before the clamp at 0 (SH at the pair's viewing direction, or sigmoid RGB)."""
    if degree is None:
        return splat_colors(p["features_dc"], p["features_rest"], None)
    campos = torch.inverse(viewmats)[:, :3, 3]
    coeffs = torch.cat((p["features_dc"][:, None, :], p["features_rest"]), dim=1)
    return sh_to_color(degree, p["means"] - campos[cids], coeffs) + 0.5


@torch.no_grad()
def pair_sh_bases(p: Dict[str, Tensor], cids: Tensor, viewmats: Tensor, degree: int) -> Tensor:
    """[nnz, (degree+1)^2] the SH bases at each pair's viewing direction (what `sh_squared_gradients` needs)."""
    campos = torch.inverse(viewmats)[:, :3, 3]
    return sh_bases(degree, p["means"] - campos[cids])


def _render_linearized(splat: Splat, params, cids, gids, radii, viewmats, Ks, width, height, grad_params, rasterize,
                       backgrounds, in_frustum) -> PairRender:
    """`render_pairs(linearize=True)`: the rasterizer's inputs as leaves, plus each pair's projection Jacobian."""
    degree = splat.sh_degree
    # With SH the coefficients are left to the colour gradient; sigmoid RGB colours are chained like the rest.
    theta = [n for n in grad_params if n in params]
    leaves = {n: t[gids] for n, t in params.items()}
    like = {"dtype": leaves["means"].dtype, "device": leaves["means"].device}
    raster = [torch.empty(gids.shape[0], w, **like) for _, w in RASTER_INPUTS]
    depths = torch.empty(gids.shape[0], **like)
    widths = [leaves[n].shape[1:].numel() for n in theta]
    offsets = [sum(widths[:k]) for k in range(len(theta))]
    jac = leaves["means"].new_zeros(gids.shape[0], 9, sum(widths))
    mask = torch.empty(gids.shape[0], 3, dtype=jac.dtype, device=jac.device) if degree is not None else None
    for start in range(0, gids.shape[0], JACOBIAN_PAIRS_PER_CHUNK):
        rows = slice(start, start + JACOBIAN_PAIRS_PER_CHUNK)
        with torch.enable_grad(), record_function("pair_render.jacobian"):
            p = {n: t[rows].requires_grad_(n in theta) for n, t in leaves.items()}
            proj, opacities = project_pairs(splat, p, cids[rows], viewmats, Ks, width, height)
            unclamped = pair_colors(p, cids[rows], viewmats, degree)
            colors = torch.clamp_min(unclamped, 0.0)
            # Rows of every pair's Jacobian at once (the pairs are independent), by batched backward passes: the
            # 6 geometric rows through the projection, the 3 colour rows through the SH only (a single 9-row pass
            # would carry every row through both graphs).
            for first, y in ((0, torch.cat((proj["means2d"], proj["conics"], opacities[:, None]), 1)), (6, colors)):
                if not theta or not y.requires_grad:
                    continue
                k = y.shape[1]
                eye = torch.eye(k, dtype=y.dtype, device=y.device)[:, None, :].expand(k, y.shape[0], k)
                grads = torch.autograd.grad(y, [p[n] for n in theta], eye, is_grads_batched=True, allow_unused=True)
                for g, w, o in zip(grads, widths, offsets, strict=True):
                    if g is not None:
                        jac[rows, first : first + k, o : o + w] = g.reshape(k, y.shape[0], w).transpose(0, 1)
        for leaf, part in zip(raster, (proj["means2d"], proj["conics"], opacities[:, None], colors), strict=True):
            leaf[rows] = part.detach()
        depths[rows] = proj["depths"].detach()
        if mask is not None:
            mask[rows] = unclamped.detach() > 0
    bases = pair_sh_bases(leaves, cids, viewmats, degree) if degree is not None else None
    raster = [t.requires_grad_() for t in raster]
    means2d, conics, opacities, colors = raster
    with record_function("pair_render.rasterize"):
        image, _ = rasterize(means2d, conics, colors, opacities[:, 0], radii, depths, cids, gids, viewmats.shape[0],
                             width, height, backgrounds)
    return PairRender(
        image=image, leaves=leaves, camera_ids=cids, gaussian_ids=gids, sh_bases=bases, pairs_in_frustum=in_frustum,
        raster_inputs=raster, jacobian=jac, jacobian_params=theta, color_mask=mask,
    )


def project_pairs(
    splat: Splat, p: Dict[str, Tensor], cids: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int
):
    """gsplat's projection of each pair (its raw `means`, `quats`, `scales`, `opacities` in `p`, [nnz, ...]) into
    its view: (`_project`'s dict, the opacities splatfacto rasterizes with)."""
    cov = quat_scale_to_covar(p["quats"], torch.exp(p["scales"]))
    proj = project(p["means"], cov, viewmats[cids], Ks[cids], width, height, EPS2D, False)
    alphas = splat_opacities(p["opacities"])
    if splat.antialiased:
        alphas = alphas * proj["compensations"]
    return proj, alphas


def composited(splat: Splat, params, cids, gids, radii, viewmats, Ks, width, height, rasterize, backgrounds) -> Tensor:
    """[nnz] bool: whether each pair is composited into at least one pixel. With zero colours that require grad
    and an all-ones upstream gradient, a pair's colour gradient is sum over pixels of alpha * T: > 0 exactly
    when it is composited somewhere (no cancellation: every term is >= 0)."""
    with torch.no_grad():
        pair_params = {n: params[n][gids] for n in ("means", "quats", "scales", "opacities")}
        proj, opacities = project_pairs(splat, pair_params, cids, viewmats, Ks, width, height)
    probe = torch.zeros(gids.shape[0], 3, dtype=opacities.dtype, device=opacities.device, requires_grad=True)
    with torch.enable_grad():
        image, _ = rasterize(proj["means2d"], proj["conics"], probe, opacities, radii, proj["depths"], cids, gids,
                             viewmats.shape[0], width, height, backgrounds)
        (weight,) = torch.autograd.grad(image.sum(), probe)
    return weight[:, 0] > 0


def sh_squared_gradients(sh_bases: Tensor, color_grad_sq: Tensor, n_rest: int) -> Tuple[Tensor, Tensor]:
    """Squared gradients of each pair's SH coefficients from its squared colour gradient: colour = sum_k B_k c_k,
    so dL/dc_k = B_k * d and (dL/dc_k)^2 = B_k^2 * d^2 (also for a probe-mean of d^2, B being fixed).
    sh_bases [nnz, K], color_grad_sq [nnz, 3] -> (features_dc [nnz, 3], features_rest [nnz, n_rest, 3]); the
    coefficients above the active degree get zero."""
    b2 = sh_bases.square()
    dc = b2[:, :1] * color_grad_sq
    rest = color_grad_sq.new_zeros(color_grad_sq.shape[0], n_rest, 3)
    used = min(b2.shape[1] - 1, n_rest)
    rest[:, :used] = b2[:, 1 : 1 + used, None] * color_grad_sq[:, None, :]
    return dc, rest


def _rasterize_cpu(means2d, conics, colors, opacities, radii, depths, cids, gids, C, width, height, backgrounds):
    return rasterize_pairs(means2d, conics, colors, opacities, radii, depths, cids, C, width, height, TILE_SIZE,
                           backgrounds)


def _rasterize_gsplat(means2d, conics, colors, opacities, radii, depths, cids, gids, C, width, height, backgrounds):
    # Imported here: on a machine without CUDA gsplat's kernels must never be touched (nvcc starts a JIT build).
    from gsplat.cuda._wrapper import isect_offset_encode, isect_tiles, rasterize_to_pixels

    tile_w, tile_h = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    _, isect_ids, flatten_ids = isect_tiles(
        means2d.detach().contiguous(), radii.int().contiguous(), depths.detach().contiguous(), TILE_SIZE, tile_w,
        tile_h, packed=True, n_cameras=C, camera_ids=cids.contiguous(), gaussian_ids=gids.contiguous(),
    )
    offsets = isect_offset_encode(isect_ids, C, tile_w, tile_h)
    return rasterize_to_pixels(
        means2d.contiguous(), conics.contiguous(), colors.contiguous(), opacities.contiguous(), width, height,
        TILE_SIZE, offsets, flatten_ids, backgrounds=backgrounds, packed=True,
    )
