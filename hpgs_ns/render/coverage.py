"""Forward-only per-pair renders for the `coverage` selector: how much each (view, Gaussian) pair shows, and images
of per-pair values.

A view's visible pairs are found and projected as `pair_render` does it (`visible_pairs`, `project_pairs`: gsplat's
EWA maths with the settings and activations of the model's own renders, `render.rasterize`). Two things are then
computed from them, on gsplat's kernels (CUDA) or on the pure-PyTorch twin (`cpu_raster`), with everything but the
rasterizer call shared:

- `max_weights`: each pair's largest compositing weight over the view's pixels, max_p T(p) alpha(p). gsplat returns
  no per-Gaussian reduction of its weights (its `rasterize_to_pixels` gives images only), so this is written here:
  on CUDA from `rasterize_to_indices_in_range`'s (Gaussian, pixel) list, on the CPU by walking the twin's tiles.
- `render_values`: the image of one scalar per pair, composited front to back over a constant background.

Eval-mode, no gradients. The CPU path is tested against explicit per-pixel compositing, the CUDA path against the
CPU one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from hpgs_ns.cpu_raster import (
    ALPHA_MIN,
    DEPTH_BLOCK,
    TRANSMITTANCE_MIN,
    _alpha_block,
    _below,
    _gather_block,
    _Plan,
    _transmittance,
    quat_scale_to_covar,
)
from hpgs_ns.render.pair_render import Splat, _rasterize_cpu, _rasterize_gsplat, project_pairs, visible_pairs
from hpgs_ns.render.rasterize import TILE_SIZE


@dataclass
class ProjectedPairs:
    """The (view, Gaussian) pairs of C views of one size that gsplat would rasterize, projected."""

    camera_ids: Tensor
    """[nnz] which view of the batch each pair belongs to."""
    gaussian_ids: Tensor
    """[nnz] which Gaussian of the splat."""
    means2d: Tensor
    """[nnz, 2] pixel coordinates of the projected centre."""
    conics: Tensor
    """[nnz, 3] inverse of the blurred 2D covariance (xx, xy, yy)."""
    opacities: Tensor
    """[nnz] opacity as rasterized (times the low-pass compensation when the splat is antialiased)."""
    depths: Tensor
    """[nnz] camera-space z."""
    radii: Tensor
    """[nnz] int32 footprint radius in pixels (which tiles a pair touches)."""
    n_cameras: int
    width: int
    height: int
    backend: str
    """`gsplat` or `cpu`: the splat's rasterizer."""


@torch.no_grad()
def project_visible(splat: Splat, viewmats: Tensor, Ks: Tensor, width: int, height: int) -> ProjectedPairs:
    """The pairs of `splat` seen by C views ([C, 4, 4] world-to-camera, [C, 3, 3] intrinsics, all `width` x
    `height`), projected as the model's renders project them."""
    params = splat.params
    covars = quat_scale_to_covar(params["quats"], torch.exp(params["scales"]))
    cids, gids, radii = visible_pairs(params["means"], covars, viewmats, Ks, width, height)
    pair_params = {n: params[n][gids] for n in ("means", "quats", "scales", "opacities")}
    proj, opacities = project_pairs(splat, pair_params, cids, viewmats, Ks, width, height)
    return ProjectedPairs(
        camera_ids=cids, gaussian_ids=gids, means2d=proj["means2d"], conics=proj["conics"], opacities=opacities,
        depths=proj["depths"], radii=radii, n_cameras=viewmats.shape[0], width=width, height=height,
        backend=splat.backend,
    )


@torch.no_grad()
def max_weights(pairs: ProjectedPairs) -> Tensor:
    """[nnz] each pair's largest weight T(p) alpha(p) over its view's pixels p (T: the transmittance in front of it,
    alpha: its clamped opacity there), with gsplat's compositing rules (alpha < 1/255 skipped, a pixel stops before
    its transmittance reaches 1e-4). 0 for a pair composited nowhere."""
    if pairs.camera_ids.numel() == 0:
        return pairs.opacities.new_zeros(0)
    if pairs.backend == "gsplat":
        return _max_weights_gsplat(pairs)
    return _max_weights_cpu(pairs)


@torch.no_grad()
def render_values(pairs: ProjectedPairs, values: Tensor, background: float = 1.0) -> Tensor:
    """[C, H, W] the image of one value per pair (`values` [nnz]) composited front to back over `background`:
    sum_g T alpha value + T_final * background at every pixel."""
    C, H, W = pairs.n_cameras, pairs.height, pairs.width
    backgrounds = pairs.opacities.new_full((C, 1), background)
    if pairs.camera_ids.numel() == 0:
        return backgrounds[:, :, None].expand(C, H, W).clone()
    rasterize = _rasterize_gsplat if pairs.backend == "gsplat" else _rasterize_cpu
    image, _ = rasterize(pairs.means2d, pairs.conics, values[:, None].to(pairs.opacities), pairs.opacities, pairs.radii,
                         pairs.depths, pairs.camera_ids, pairs.gaussian_ids, C, W, H, backgrounds)
    return image[..., 0]


def _max_weights_cpu(pairs: ProjectedPairs) -> Tensor:
    """`max_weights` on `cpu_raster`'s tiles: its forward compositing walk, keeping each pair's largest weight instead
    of the colours."""
    means2d, conics, opacities = pairs.means2d, pairs.conics, pairs.opacities
    dtype = opacities.dtype
    plan = _Plan(means2d, pairs.radii.int(), pairs.depths, pairs.camera_ids.long(), pairs.n_cameras, pairs.width,
                 pairs.height, TILE_SIZE)
    best = opacities.new_zeros(opacities.shape[0])
    alpha_keep = _below(ALPHA_MIN, dtype)
    for tiles, length in plan.chunks:
        px, py, outside = plan.tile_pixels(tiles, dtype)
        T = torch.ones(px.shape, dtype=dtype, device=px.device)
        done = outside.clone()
        counts = plan.tile_counts[tiles]
        for start in range(0, length, DEPTH_BLOCK):
            live = torch.nonzero((counts > start) & ~done.all(1)).flatten()
            if live.numel() == 0:
                break  # every pixel of these tiles has stopped
            size = min(DEPTH_BLOCK, int(counts[live].max()) - start)
            T_b, done_b = T[live], done[live]
            gid, m, con, opac = _gather_block(plan, tiles[live], start, size, means2d, conics, opacities)
            alpha = _alpha_block(px[live][..., None], py[live][..., None], m, con, opac, alpha_keep)[4]
            Tc, _, w = _transmittance(torch.where(done_b, 0.0, T_b), alpha)
            best.scatter_reduce_(0, gid.reshape(-1), w.amax(1).reshape(-1), "amax")
            # As the twin's forward: the transmittance is the last running product still above the threshold.
            T[live] = torch.where(done_b, T_b, F.threshold(Tc, TRANSMITTANCE_MIN, math.inf).amin(-1))
            done[live] = done_b | (Tc[..., -1] <= TRANSMITTANCE_MIN)
    return best


def _max_weights_gsplat(pairs: ProjectedPairs) -> Tensor:
    """`max_weights` on gsplat's kernels, one view at a time: `rasterize_to_indices_in_range` lists every (pair,
    pixel) that gsplat composites, grouped by pixel and front to back, and the transmittance in front of each entry
    is the product of (1 - alpha) of the entries before it in its pixel."""
    # Imported here: on a machine without CUDA gsplat's kernels must never be touched (nvcc starts a JIT build).
    from gsplat.cuda._wrapper import isect_offset_encode, isect_tiles, rasterize_to_indices_in_range

    W, H = pairs.width, pairs.height
    tile_w, tile_h = -(-W // TILE_SIZE), -(-H // TILE_SIZE)
    best = pairs.opacities.new_zeros(pairs.opacities.shape[0])
    for c in range(pairs.n_cameras):
        rows = torch.nonzero(pairs.camera_ids == c).flatten()
        if rows.numel() == 0:
            continue
        # gsplat's index enumeration takes the unpacked layout [C, N]: this view's pairs as one camera's Gaussians.
        m2 = pairs.means2d[rows].float()[None].contiguous()
        con = pairs.conics[rows].float()[None].contiguous()
        opac = pairs.opacities[rows].float()[None].contiguous()
        _, isect_ids, flatten_ids = isect_tiles(m2, pairs.radii[rows].int()[None].contiguous(),
                                                pairs.depths[rows].float()[None].contiguous(), TILE_SIZE, tile_w, tile_h)
        offsets = isect_offset_encode(isect_ids, 1, tile_w, tile_h)
        tile_lengths = torch.bincount(isect_ids >> 32, minlength=tile_w * tile_h)
        n_batches = -(-int(tile_lengths.max()) // (TILE_SIZE * TILE_SIZE))
        # One call over every depth batch: split calls would restart stopped pixels (gsplat keeps no "done" state).
        gs, pix, _ = rasterize_to_indices_in_range(0, n_batches, torch.ones(1, H, W, device=m2.device), m2, con, opac,
                                                   W, H, TILE_SIZE, offsets, flatten_ids)
        if gs.numel() == 0:
            continue
        delta = m2[0, gs] - torch.stack([pix % W, pix // W], -1).to(m2) - 0.5
        k = con[0, gs]
        sigma = 0.5 * (k[:, 0] * delta[:, 0] ** 2 + k[:, 2] * delta[:, 1] ** 2) + k[:, 1] * delta[:, 0] * delta[:, 1]
        alpha = torch.clamp_max(opac[0, gs] * torch.exp(-sigma), 0.999).double()
        log_t = torch.log1p(-alpha)
        exclusive = torch.cumsum(log_t, 0) - log_t
        _, counts = torch.unique_consecutive(pix, return_counts=True)
        first = torch.cumsum(counts, 0) - counts
        exclusive -= torch.repeat_interleave(exclusive[first], counts)
        weights = (torch.exp(exclusive) * alpha).to(best.dtype)
        best[rows] = best.new_zeros(rows.numel()).scatter_reduce_(0, gs, weights, "amax")
    return best
