"""Render several views so that every (view, Gaussian) pair owns its own copy of the Gaussian's parameters.

A normal render shares the Gaussians between the cameras of a batch, so one backward pass returns the *sum* of
the views' gradients. FisherRF needs each view's own squared gradient; with gsplat's `rasterization` that meant
one backward per view and probe (200 candidates x 16 probes = 3200 launch-bound passes, 7.6 s on an H200).

Here the pairs whose footprint reaches a view are found first (no autograd: this is the frustum culling, so a
view costs only its visible Gaussians), their raw parameters are gathered into leaf tensors [nnz, ...], projected
in PyTorch (`cpu_raster._project`: gsplat's EWA maths), and composited by gsplat's packed `rasterize_to_pixels`
(CUDA) or its pure-PyTorch twin `cpu_raster.rasterize_pairs`. One backward pass then gives every pair's gradient:
every view's own gradient, for a whole batch of views at once.

No library offers per-view gradients of a batched render (gsplat's batched API shares the 3D parameters), which
is why this is written here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Sequence, Tuple

import torch
from torch import Tensor

from hpgs_ns.cpu_raster import _project, _quat_scale_to_covar, _sh_bases, _sh_to_color

SH_PARAMS = ("features_dc", "features_rest")
NEAR_PLANE = 0.01  # splatfacto's near plane
EPS2D = 0.3  # gsplat's default low-pass (splatfacto keeps it)
TILE_SIZE = 16
PAIRS_PER_CHUNK = 1 << 22  # (camera, Gaussian) pairs tested at once when culling (bounds memory, not results)


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


def active_sh_degree(model) -> int | None:
    """The SH degree splatfacto renders with at the model's current step (None: plain RGB colours)."""
    if model.config.sh_degree <= 0:
        return None
    return min(model.step // model.config.sh_degree_interval, model.config.sh_degree)


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
        proj = _project(means[None], covars[None], vm[:, None], K[:, None], width, height, EPS2D, False, radius_floor=0.1)
        m2, r = proj["means2d"], proj["radius"]
        valid = ok[None] & (proj["depths"] >= NEAR_PLANE) & (proj["det"] > 0) & (r > 0) & torch.isfinite(r)
        valid &= torch.isfinite(m2).all(-1) & torch.isfinite(proj["conics"]).all(-1)
        valid &= (m2[..., 0] + r > 0) & (m2[..., 0] - r < width) & (m2[..., 1] + r > 0) & (m2[..., 1] - r < height)
        c, g = torch.nonzero(valid, as_tuple=True)
        cids.append(c + start)
        gids.append(g)
        radii.append(r[c, g].int())
    return torch.cat(cids), torch.cat(gids), torch.cat(radii)


def render_pairs(
    model, viewmats: Tensor, Ks: Tensor, width: int, height: int, grad_params: Sequence[str], backend: str,
    sh_via_color: bool = False, drop_hidden: bool = False,
) -> PairRender:
    """Eval-mode RGB of C views of one size ([C, 4, 4] world-to-camera, [C, 3, 3] intrinsics), differentiable
    w.r.t. each pair's copy of `grad_params` (names of `model.gauss_params`). `backend`: "gsplat" or "cpu".

    `sh_via_color`: the SH coefficients (`features_dc`, `features_rest`) get no gradient of their own; the
    render carries `color_offset` and `sh_bases` instead, from which `sh_squared_gradients` gives theirs. The
    colour is linear in the coefficients, so this is exact, and a backward pass then writes 3 numbers per pair
    for them instead of 3 (degree + 1)^2.

    `drop_hidden`: leave out the pairs the rasterizer composites into no pixel (behind opaque surfaces, or alpha
    below 1/255 everywhere). They change no pixel and get exactly zero gradient, so the image and every kept
    pair's gradient are the same; finding them costs one forward and backward without parameter gradients."""
    params = {n: t.detach() for n, t in model.gauss_params.items()}
    C = viewmats.shape[0]
    with torch.no_grad():
        covars = _quat_scale_to_covar(params["quats"], torch.exp(params["scales"]))
    cids, gids, radii = visible_pairs(params["means"], covars, viewmats, Ks, width, height)
    in_frustum = int(cids.numel())
    rasterize = _rasterize_gsplat if backend == "gsplat" else _rasterize_cpu
    backgrounds = model.background_color.to(viewmats).expand(C, 3).contiguous()
    if drop_hidden and in_frustum:
        keep = composited(model, params, cids, gids, radii, viewmats, Ks, width, height, rasterize, backgrounds)
        cids, gids, radii = cids[keep], gids[keep], radii[keep]
    degree = active_sh_degree(model)
    via_color = sh_via_color and degree is not None
    if via_color:
        grad_params = [n for n in grad_params if n not in SH_PARAMS]
    leaves = {n: t[gids].requires_grad_(n in grad_params) for n, t in params.items()}

    proj, opacities = project_pairs(model, leaves, cids, viewmats, Ks, width, height)
    offset = bases = None
    if degree is None:
        colors = torch.sigmoid(leaves["features_dc"])
    else:
        campos = torch.inverse(viewmats)[:, :3, 3]
        dirs = leaves["means"] - campos[cids]
        coeffs = torch.cat((leaves["features_dc"][:, None, :], leaves["features_rest"]), dim=1)
        colors = _sh_to_color(degree, dirs, coeffs) + 0.5
        if via_color:
            offset = torch.zeros_like(colors, requires_grad=True)
            colors = colors + offset
            with torch.no_grad():
                bases = _sh_bases(degree, dirs)
        colors = torch.clamp_min(colors, 0.0)
    image, _ = rasterize(proj["means2d"], proj["conics"], colors, opacities, radii, proj["depths"], cids, gids, C, width, height, backgrounds)
    return PairRender(
        image=image, leaves=leaves, camera_ids=cids, gaussian_ids=gids, color_offset=offset, sh_bases=bases,
        pairs_in_frustum=in_frustum,
    )


def project_pairs(model, p: Dict[str, Tensor], cids: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int):
    """gsplat's projection of each pair (its raw `means`, `quats`, `scales`, `opacities` in `p`, [nnz, ...]) into
    its view: (`_project`'s dict, the opacities splatfacto rasterizes with)."""
    cov = _quat_scale_to_covar(p["quats"], torch.exp(p["scales"]))
    proj = _project(p["means"], cov, viewmats[cids], Ks[cids], width, height, EPS2D, False)
    opacities = torch.sigmoid(p["opacities"]).reshape(-1)
    if model.config.rasterize_mode == "antialiased":
        opacities = opacities * proj["compensations"]
    return proj, opacities


def composited(model, params, cids, gids, radii, viewmats, Ks, width, height, rasterize, backgrounds) -> Tensor:
    """[nnz] bool: whether each pair is composited into at least one pixel. With zero colours that require grad
    and an all-ones upstream gradient, a pair's colour gradient is sum over pixels of alpha * T: > 0 exactly
    when it is composited somewhere (no cancellation: every term is >= 0)."""
    with torch.no_grad():
        pair_params = {n: params[n][gids] for n in ("means", "quats", "scales", "opacities")}
        proj, opacities = project_pairs(model, pair_params, cids, viewmats, Ks, width, height)
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
    from hpgs_ns.cpu_raster import rasterize_pairs

    return rasterize_pairs(means2d, conics, colors, opacities, radii, depths, cids, C, width, height, TILE_SIZE, backgrounds)


def _rasterize_gsplat(means2d, conics, colors, opacities, radii, depths, cids, gids, C, width, height, backgrounds):
    # Imported here: on a machine without CUDA gsplat's kernels must never be touched (nvcc starts a JIT build).
    from gsplat.cuda._wrapper import isect_offset_encode, isect_tiles, rasterize_to_pixels

    tile_w, tile_h = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    _, isect_ids, flatten_ids = isect_tiles(
        means2d.detach().contiguous(), radii.int().contiguous(), depths.detach().contiguous(), TILE_SIZE, tile_w, tile_h,
        packed=True, n_cameras=C, camera_ids=cids.contiguous(), gaussian_ids=gids.contiguous(),
    )
    offsets = isect_offset_encode(isect_ids, C, tile_w, tile_h)
    return rasterize_to_pixels(
        means2d.contiguous(), conics.contiguous(), colors.contiguous(), opacities.contiguous(), width, height, TILE_SIZE,
        offsets, flatten_ids, backgrounds=backgrounds, packed=True,
    )
