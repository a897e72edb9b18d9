"""Pure-PyTorch twin of gsplat 1.4.0's `rasterization` (3D Gaussian splatting), for machines without CUDA.

`rasterization(...)` takes gsplat 1.4.0's arguments and returns what it returns: `(render_colors [C,H,W,X],
render_alphas [C,H,W,1], meta)`. It follows gsplat's CUDA kernels (fully_fused_projection, spherical_harmonics,
isect_tiles, rasterize_to_pixels) convention for convention, so a splat trained or scored on the CPU behaves as on
the GPU. It is differentiable w.r.t. means, quats, scales, opacities, colors/SH, viewmats and backgrounds (not Ks,
as in gsplat).

Algorithm
---------
1. Projection, for every (camera, Gaussian) pair, first without autograd to decide which pairs are *valid*:
   world->camera, covariance R S S^T R^T, EWA Jacobian with gsplat's frustum clamp (1.3 x the half field of view),
   2D covariance + eps2d on the diagonal (the low-pass; "antialiased" multiplies opacity by
   sqrt(det(cov) / det(cov + eps2d I)), differentiated as gsplat does: 0.5 / (sqrt + 1e-6)), conic = inverse,
   radius = ceil(3 sqrt(b + sqrt(max(b^2 - det, floor)))), b = trace / 2: the largest eigenvalue, with gsplat's
   floor of 0.01 (unpacked) or 0.1 (packed: gsplat's packed kernel differs there, and so does this). A pair is
   culled as in gsplat (depth outside [near, far], det <= 0, radius <= radius_clip, 3-sigma box off-screen) and
   also when anything about it is not finite or could overflow (NaN/inf parameters, zero quaternion, a radius beyond
   int32, a quadratic form that would overflow). The differentiable projection is then recomputed on the valid
   pairs only, so an invalid Gaussian never enters a graph: its gradient is exactly zero and nothing non-finite
   can leak through a masked branch.
2. Colours: SH evaluated as gsplat's CUDA kernel (Sloan's formulas, view direction from the camera centre), then
   clamp_min(color + 0.5, 0); depth appended for "D"/"ED"/"RGB+D"/"RGB+ED".
3. Tiling: every valid pair touches the 16x16 tiles its square of half-side `radius` covers (gsplat's floor/ceil
   rule). The (tile, pair) intersections are sorted by (camera, tile, depth), stable, as gsplat's radix sort.
4. Compositing (`_RasterizeToPixels`, a custom autograd Function with an analytic backward): tiles are grouped
   into chunks of similar length and walked front to back in depth blocks, so each step is a dense
   [tiles, tile pixels, gaussians] tensor of bounded size (memory does not grow with N). A Gaussian is shaded at
   every pixel of every tile it touches: sigma = 1/2 d^T conic d with d = mean2d - pixel centre,
   alpha = min(0.999, opacity exp(-sigma)); alpha < 1/255 or sigma < 0 is skipped; a pixel stops (exclusively)
   at the Gaussian that would bring its transmittance to <= 1e-4. Transmittance is a sequential running product
   (torch.cumprod), so the stop decisions match the CUDA loop. Tiles whose pixels have all stopped are dropped
   from later blocks, which keeps the cost proportional to covered pixels, not N x pixels. The backward
   replays the blocks from saved per-block transmittances, back to front, with suffix sums (no division chain),
   and also returns the per-pixel absolute means2d gradients summed (`means2d.absgrad`, AbsGS) when asked.
5. Background: colour + T_final * background; "ED" divides the depth channel by alpha.clamp(min=1e-10).

Everything runs in the dtype of `means` (float32 or float64; the tests check gradients in float64).

Speed: 10k Gaussians at 128x128, splatfacto settings, forward+backward in about 0.35 s on one core of a shared
2-core machine. The work is a few dozen elementwise ops per step on ~2 MB tensors; where the cores are
oversubscribed, OpenMP's hand-offs between threads dominate (several times slower with 2 threads than with 1), so
prefer OMP_NUM_THREADS=1 there.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "rasterization", "rasterize_pairs", "project", "quat_scale_to_covar", "sh_bases", "sh_to_color", "UnsupportedArgumentError",
]

ALPHA_MAX = 0.999  # alpha clamp (gsplat: min(0.999f, ...))
ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped
TRANSMITTANCE_MIN = 1e-4  # a pixel stops before its transmittance falls to this or below
SIGMA_MAX = 60.0  # exp(-60) * opacity < 1/255 for any opacity below 1e23: such a pixel is skipped either way
# A compositing step holds a few [tiles, gaussians, pixels] tensors of at most this many elements each.
CHUNK_ELEMENTS = 1 << 19
DEPTH_BLOCK = 64  # gaussians per tile per step
_INT32_MAX = 2**31 - 1
_RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


class UnsupportedArgumentError(ValueError):
    """An argument (or a value of one) that this CPU rasterizer does not support."""


# ----------------------------------------------------------------------------------------------------------------
# Projection
# ----------------------------------------------------------------------------------------------------------------


def _mm(a: Tensor, b: Tensor) -> Tensor:
    """a @ b for stacks of tiny matrices ([..., n, k] @ [..., k, m]).

    On CUDA as a sum of broadcast outer products, not `@`: for millions of 3x3 matrices batched matmul launches
    cuBLAS GEMMs tile by tile, which was most of the GPU time of a Fisher round when profiled on an H100. On the
    CPU `@` is the faster one (about 2x)."""
    return _mm_broadcast(a, b) if a.is_cuda else a @ b


def _mm_broadcast(a: Tensor, b: Tensor) -> Tensor:
    out = a[..., :, 0, None] * b[..., None, 0, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k, None] * b[..., None, k, :]
    return out


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """Covariance R S S^T R^T from (unnormalised, wxyz) quaternions [..., 4] and scales [..., 3] -> [..., 3, 3]."""
    q = quats * torch.rsqrt((quats * quats).sum(-1, keepdim=True))
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))
    M = R * scales[..., None, :]
    return _mm(M, M.transpose(-1, -2))


class _SqrtCompensation(torch.autograd.Function):
    """sqrt(max(x, 0)) with gsplat's gradient 0.5 / (sqrt + 1e-6): finite at 0 (zero-scale Gaussians)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        y = x.clamp_min(0).sqrt()
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        (y,) = ctx.saved_tensors
        return g * 0.5 / (y + 1e-6)


def project(
    means: Tensor,  # [..., 3] world
    covars: Tensor,  # [..., 3, 3] world
    viewmats: Tensor,  # [..., 4, 4] world-to-camera
    Ks: Tensor,  # [..., 3, 3]
    width: int,
    height: int,
    eps2d: float,
    ortho: bool,
    radius_floor: float = 0.01,
) -> Dict[str, Tensor]:
    """EWA projection as gsplat's `fully_fused_projection` kernel (broadcasts over leading dims).

    `radius_floor` is the floor under b^2 - det in the radius: 0.01 in gsplat 1.4.0's unpacked kernel, 0.1 in its
    packed one (an inconsistency of gsplat that a twin has to copy).

    Returns means2d [..., 2], depths [...], conics [..., 3] (inverse of the blurred 2D covariance: xx, xy, yy),
    compensations [...], det [...] (of the blurred covariance) and radius [...] (float, not differentiable)."""
    R = viewmats[..., :3, :3]
    t = viewmats[..., :3, 3]
    mean_c = _mm(R, means[..., None])[..., 0] + t
    cov_c = _mm(_mm(R, covars), R.transpose(-1, -2))
    x, y, z = mean_c.unbind(-1)
    fx, fy, cx, cy = Ks[..., 0, 0], Ks[..., 1, 1], Ks[..., 0, 2], Ks[..., 1, 2]
    zeros = torch.zeros_like(z)
    if ortho:
        J = torch.stack([fx + zeros, zeros, zeros, zeros, fy + zeros, zeros], -1)
        mean2d = torch.stack([fx * x + cx, fy * y + cy], -1)
    else:
        # gsplat clamps the Jacobian's x/z, y/z to 1.3 x the half field of view (outside: frozen direction).
        lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
        lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
        lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
        lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
        rz = 1.0 / z
        rz2 = rz * rz
        tx = z * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x * rz))
        ty = z * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y * rz))
        J = torch.stack([fx * rz, zeros, -fx * tx * rz2, zeros, fy * rz, -fy * ty * rz2], -1)
        mean2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], -1)
    J = J.reshape(J.shape[:-1] + (2, 3))
    cov2d = _mm(_mm(J, cov_c), J.transpose(-1, -2))
    a, b, c = cov2d[..., 0, 0], cov2d[..., 0, 1], cov2d[..., 1, 1]
    det_orig = a * c - b * b
    a = a + eps2d
    c = c + eps2d
    det = a * c - b * b
    comp = _SqrtCompensation.apply(det_orig / det)
    conics = torch.stack([c / det, -b / det, a / det], -1)
    with torch.no_grad():
        half_trace = 0.5 * (a + c)
        v1 = half_trace + torch.sqrt(torch.clamp_min(half_trace * half_trace - det, radius_floor))
        radius = torch.ceil(3.0 * torch.sqrt(v1))
    return {"means2d": mean2d, "depths": z, "conics": conics, "compensations": comp, "det": det, "radius": radius}


# ----------------------------------------------------------------------------------------------------------------
# Spherical harmonics (gsplat's CUDA evaluation: Sloan, "Efficient Spherical Harmonic Evaluation", JCGT 2013)
# ----------------------------------------------------------------------------------------------------------------


def sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """Real SH bases up to `degree` (0..4) at the directions dirs [M, 3] (not normalised) -> [M, (degree+1)^2]."""
    bases = [torch.full_like(dirs[..., 0], 0.2820947917738781)]
    if degree >= 1:
        # The directions of valid pairs are never zero (the Gaussian would sit on the camera plane).
        n = dirs * torch.rsqrt((dirs * dirs).sum(-1, keepdim=True).clamp_min(1e-30))
        x, y, z = n.unbind(-1)
        bases += [-0.48860251190292 * y, 0.48860251190292 * z, -0.48860251190292 * x]
        if degree >= 2:
            z2 = z * z
            fTmp0B = -1.092548430592079 * z
            fC1 = x * x - y * y
            fS1 = 2.0 * x * y
            pSH6 = 0.9461746957575601 * z2 - 0.3153915652525201
            bases += [0.5462742152960395 * fS1, fTmp0B * y, pSH6, fTmp0B * x, 0.5462742152960395 * fC1]
            if degree >= 3:
                fTmp0C = -2.285228997322329 * z2 + 0.4570457994644658
                fTmp1B = 1.445305721320277 * z
                fC2 = x * fC1 - y * fS1
                fS2 = x * fS1 + y * fC1
                pSH12 = z * (1.865881662950577 * z2 - 1.119528997770346)
                bases += [
                    -0.5900435899266435 * fS2, fTmp1B * fS1, fTmp0C * y, pSH12,
                    fTmp0C * x, fTmp1B * fC1, -0.5900435899266435 * fC2,
                ]
                if degree >= 4:
                    fTmp0D = z * (-4.683325804901025 * z2 + 2.007139630671868)
                    fTmp1C = 3.31161143515146 * z2 - 0.47308734787878
                    fTmp2B = -1.770130769779931 * z
                    fC3 = x * fC2 - y * fS2
                    fS3 = x * fS2 + y * fC2
                    pSH20 = 1.984313483298443 * z * pSH12 - 1.006230589874905 * pSH6
                    bases += [
                        0.6258357354491763 * fS3, fTmp2B * fS2, fTmp1C * fS1, fTmp0D * y, pSH20,
                        fTmp0D * x, fTmp1C * fC1, fTmp2B * fC2, 0.6258357354491763 * fC3,
                    ]
    return torch.stack(bases, -1)


def sh_to_color(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """dirs [M, 3], coeffs [M, K, 3] with (degree+1)^2 <= K -> colors [M, 3] (before the +0.5 and clamp)."""
    k = (degree + 1) ** 2
    return _mm(sh_bases(degree, dirs)[:, None, :], coeffs[:, :k, :])[:, 0]


# ----------------------------------------------------------------------------------------------------------------
# Tile intersections
# ----------------------------------------------------------------------------------------------------------------


def _depth_sort_key(depths: Tensor) -> Tensor:
    """Order-preserving map of float32 depths to int64 in [0, 2^32) (gsplat sorts the float32 bits)."""
    bits = depths.detach().float().contiguous().view(torch.int32).long()
    return torch.where(bits >= 0, bits + 2**31, -1 - bits)


class _Plan:
    """Sorted tile intersections and the chunk schedule of one `rasterization` call (no tensors need grad)."""

    def __init__(
        self,
        means2d: Tensor,  # [M, 2] of the valid pairs (detached)
        radii: Tensor,  # [M] int
        depths: Tensor,  # [M] (detached)
        camera_ids: Tensor,  # [M] int64
        n_cameras: int,
        width: int,
        height: int,
        tile_size: int,
    ):
        device = means2d.device
        self.C, self.width, self.height, self.tile_size = n_cameras, width, height, tile_size
        self.tile_width = tw = math.ceil(width / tile_size)
        self.tile_height = th = math.ceil(height / tile_size)
        self.n_tiles = tw * th
        self.P = tile_size * tile_size
        M = means2d.shape[0]

        # gsplat's isect_tiles: tile_min = clamp(floor((x - r) / ts)), tile_max = clamp(ceil((x + r) / ts)), float32.
        m2 = means2d.float()
        tile_r = radii.float() / tile_size
        tx, ty = m2[:, 0] / tile_size, m2[:, 1] / tile_size
        x0 = torch.floor(tx - tile_r).clamp(0, tw).long()
        x1 = torch.ceil(tx + tile_r).clamp(0, tw).long()
        y0 = torch.floor(ty - tile_r).clamp(0, th).long()
        y1 = torch.ceil(ty + tile_r).clamp(0, th).long()
        counts = (x1 - x0) * (y1 - y0)
        self.tiles_per_gauss = counts.int()
        n_isects = int(counts.sum())
        pair = torch.repeat_interleave(torch.arange(M, device=device), counts)
        local = torch.arange(n_isects, device=device) - (torch.cumsum(counts, 0) - counts)[pair]
        span = (x1 - x0)[pair]
        tile = (y0[pair] + local // span) * tw + x0[pair] + local % span
        gtile = camera_ids[pair] * self.n_tiles + tile  # camera-major global tile id
        key = gtile * 2**32 + _depth_sort_key(depths)[pair]
        order = torch.sort(key, stable=True).indices  # stable: equal depths keep pair order, as cub's radix sort
        self.flatten = pair[order]  # [n_isects] -> valid pair index, sorted by (camera, tile, depth)
        gtile_sorted = gtile[order]
        self.gtile_sorted = gtile_sorted
        tile_counts = torch.bincount(gtile_sorted, minlength=self.C * self.n_tiles)
        self.tile_counts = tile_counts
        self.tile_offsets = torch.cumsum(tile_counts, 0) - tile_counts

        # Chunks: non-empty tiles by decreasing length, grouped so that a step is at most CHUNK_ELEMENTS.
        nonempty = torch.nonzero(tile_counts > 0).flatten()
        lengths = tile_counts[nonempty]
        lengths, perm = torch.sort(lengths, descending=True, stable=True)
        tiles_sorted = nonempty[perm]
        self.chunks: List[Tuple[Tensor, int]] = []
        lengths_list = lengths.tolist()
        i = 0
        while i < len(lengths_list):
            block = min(DEPTH_BLOCK, lengths_list[i])
            n = max(1, CHUNK_ELEMENTS // (block * self.P))
            self.chunks.append((tiles_sorted[i : i + n], lengths_list[i]))
            i += n

        # Pixel centres of every tile (tile-local pixel p = row * ts + col).
        p = torch.arange(self.P, device=device)
        self.local_x = (p % tile_size).double() + 0.5
        self.local_y = (p // tile_size).double() + 0.5

    def tile_pixels(self, gtiles: Tensor, dtype: torch.dtype) -> Tuple[Tensor, Tensor, Tensor]:
        """Pixel centres px, py [T, P] of the global tiles [T] and whether each pixel lies outside the image."""
        tile = gtiles % self.n_tiles
        ox = ((tile % self.tile_width) * self.tile_size).double()
        oy = ((tile // self.tile_width) * self.tile_size).double()
        px = ox[:, None] + self.local_x[None, :]
        py = oy[:, None] + self.local_y[None, :]
        outside = (px >= self.width) | (py >= self.height)
        return px.to(dtype), py.to(dtype), outside

    def to_tiles(self, img: Tensor) -> Tensor:
        """[C, H, W, D] -> tile-major [C * n_tiles, P, D] (zero padded)."""
        C, H, W, D = img.shape
        ts = self.tile_size
        img = F.pad(img, (0, 0, 0, self.tile_width * ts - W, 0, self.tile_height * ts - H))
        img = img.reshape(C, self.tile_height, ts, self.tile_width, ts, D).permute(0, 1, 3, 2, 4, 5)
        return img.reshape(C * self.n_tiles, self.P, D)

    def from_tiles(self, tiles: Tensor) -> Tensor:
        """Tile-major [C * n_tiles, P, D] -> [C, H, W, D]."""
        D = tiles.shape[-1]
        ts = self.tile_size
        img = tiles.reshape(self.C, self.tile_height, self.tile_width, ts, ts, D).permute(0, 1, 3, 2, 4, 5)
        img = img.reshape(self.C, self.tile_height * ts, self.tile_width * ts, D)
        return img[:, : self.height, : self.width].contiguous()


# ----------------------------------------------------------------------------------------------------------------
# Compositing
# ----------------------------------------------------------------------------------------------------------------
# Layout of a step: [n tiles, P pixels, B gaussians], gaussians innermost so that the running product and the
# suffix sums run along contiguous memory. Masks are kept as float 0/1 (float<->bool mixing is slow on CPU) and
# "skip" is expressed with F.threshold, which also maps NaN to the skip value.


def _below(x: float, dtype: torch.dtype) -> float:
    """The largest value of `dtype` below x: `F.threshold(t, _below(x), v)` keeps t >= x, replaces the rest."""
    return torch.nextafter(torch.tensor(x, dtype=dtype), torch.tensor(-math.inf, dtype=dtype)).item()


class _Block:
    """One depth block of one chunk: the chunk rows it covers (None: all), its slots, the state before it."""

    __slots__ = ("rows", "start", "size", "T0")

    def __init__(self, rows: Optional[Tensor], start: int, size: int, T0: Tensor):
        self.rows, self.start, self.size, self.T0 = rows, start, size, T0


def _gather_block(plan: _Plan, tiles: Tensor, start: int, size: int, means2d: Tensor, conics: Tensor,
                  opacities: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pair ids gid [n, B] of the slots [start, start+size) of each tile, their means2d [n, B, 2], conics
    [n, B, 3] and opacities [n, B] (0 on the padding slots of shorter tiles, which makes them skipped)."""
    slot = start + torch.arange(size, device=tiles.device)
    ok = slot[None, :] < plan.tile_counts[tiles][:, None]
    isect = (plan.tile_offsets[tiles][:, None] + slot[None, :]).clamp_max(plan.flatten.shape[0] - 1)
    gid = plan.flatten[isect]
    return gid, means2d[gid], conics[gid], opacities[gid] * ok


def _alpha_block(px: Tensor, py: Tensor, m: Tensor, con: Tensor, opac: Tensor, alpha_keep: float):
    """px, py [n, P, 1]; m [n, B, 2]; con [n, B, 3]; opac [n, B] -> dx, dy, vis = exp(-sigma), alpha_raw =
    opac * vis and alpha [n, P, B] (clamped to 0.999, set to 0 where skipped: sigma < 0 or alpha < 1/255)."""
    dx = m[:, None, :, 0] - px  # delta = mean - pixel centre, as gsplat
    dy = m[:, None, :, 1] - py
    a, b, c = con[:, None, :, 0], con[:, None, :, 1], con[:, None, :, 2]
    sigma = torch.addcmul(b * dy, 0.5 * a, dx).mul_(dx).addcmul_((0.5 * c) * dy, dy)
    # sigma < 0 (or NaN) is skipped: mapped to SIGMA_MAX, whose alpha is far below 1/255. Capping sigma also keeps
    # exp() out of the denormal range, where CPUs are ~10x slower.
    F.threshold(sigma, _below(0.0, sigma.dtype), SIGMA_MAX, inplace=True).clamp_max_(SIGMA_MAX)
    vis = sigma.neg_().exp_()
    alpha_raw = vis * opac[:, None, :]
    alpha = F.threshold(alpha_raw.clamp_max(ALPHA_MAX), alpha_keep, 0.0, inplace=True)
    return dx, dy, vis, alpha_raw, alpha


def _transmittance(T0: Tensor, alpha: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """T0 [n, P] (0 for pixels already stopped), alpha [n, P, B] -> running products Tc [n, P, B+1] (Tc[..., k]
    is the transmittance in front of Gaussian k), inclusion mask inc (float) and weights w = alpha T inc."""
    n, P, B = alpha.shape
    Tc = torch.empty((n, P, B + 1), dtype=alpha.dtype, device=alpha.device)
    Tc[..., 0] = T0
    torch.sub(1.0, alpha, out=Tc[..., 1:])
    Tc.cumprod_(-1)  # sequential, in the CUDA loop's order: the stop decisions match
    inc = torch.empty_like(alpha)
    torch.gt(Tc[..., 1:], TRANSMITTANCE_MIN, out=inc)  # stop exclusively at the Gaussian reaching <= 1e-4
    w = alpha * Tc[..., :-1]
    w.mul_(inc)
    return Tc, inc, w


class _RasterizeToPixels(torch.autograd.Function):
    """Front-to-back compositing of the valid pairs -> colors [C, H, W, D], final transmittance [C, H, W, 1]."""

    @staticmethod
    def forward(
        ctx,
        means2d_meta: Tensor,  # [C, N, 2] or [nnz, 2]: meta["means2d"], receives .absgrad
        rows: Optional[Tensor],  # [M] rows of means2d_meta.reshape(-1, 2) holding the valid pairs (None: all)
        conics: Tensor,  # [M, 3]
        colors: Tensor,  # [M, D]
        opacities: Tensor,  # [M]
        plan: _Plan,
        absgrad: bool,
    ) -> Tuple[Tensor, Tensor]:
        dtype, device = colors.dtype, colors.device
        means2d = means2d_meta.reshape(-1, 2)
        if rows is not None:
            means2d = means2d[rows]
        D = colors.shape[-1]
        colors_t = colors.t()  # [D, M]
        alpha_keep = _below(ALPHA_MIN, dtype)
        out = torch.zeros((plan.C * plan.n_tiles, D, plan.P), dtype=dtype, device=device)
        T_out = torch.ones((plan.C * plan.n_tiles, plan.P), dtype=dtype, device=device)
        schedule = []
        for tiles, length in plan.chunks:
            px, py, outside = plan.tile_pixels(tiles, dtype)
            T = torch.ones(px.shape, dtype=dtype, device=device)
            done = outside.clone()
            acc = torch.zeros((tiles.shape[0], D, plan.P), dtype=dtype, device=device)
            counts = plan.tile_counts[tiles]
            blocks = []
            for start in range(0, length, DEPTH_BLOCK):
                live = (counts > start) & ~done.all(1)
                if not bool(live.any()):
                    break  # every pixel of these tiles has stopped: the rest of their lists is never read
                rows_b = None if bool(live.all()) else torch.nonzero(live).flatten()

                def sel(x: Tensor, rows_b: Optional[Tensor] = rows_b) -> Tensor:
                    return x if rows_b is None else x[rows_b]

                size = min(DEPTH_BLOCK, int(sel(counts).max()) - start)
                T_b, done_b = sel(T), sel(done)
                T0 = torch.where(done_b, 0.0, T_b)
                blocks.append(_Block(rows_b, start, size, T0))
                gid, m, con, opac = _gather_block(plan, sel(tiles), start, size, means2d, conics, opacities)
                alpha = _alpha_block(sel(px)[..., None], sel(py)[..., None], m, con, opac, alpha_keep)[4]
                Tc, _, w = _transmittance(T0, alpha)
                contrib = torch.bmm(colors_t[:, gid].permute(1, 0, 2), w.transpose(1, 2))  # [n, D, P]
                # The pixel's transmittance is the last running product still above the threshold.
                T_new = torch.where(done_b, T_b, F.threshold(Tc, TRANSMITTANCE_MIN, math.inf).amin(-1))
                done_new = done_b | (Tc[..., -1] <= TRANSMITTANCE_MIN)
                if rows_b is None:
                    acc += contrib
                    T, done = T_new, done_new
                else:
                    acc.index_add_(0, rows_b, contrib)
                    T = T.index_copy(0, rows_b, T_new)
                    done = done.index_copy(0, rows_b, done_new)
            out[tiles] = acc
            T_out[tiles] = T
            schedule.append((tiles, px, py, blocks, T))
        ctx.plan, ctx.schedule, ctx.absgrad, ctx.has_rows = plan, schedule, absgrad, rows is not None
        ctx.save_for_backward(means2d_meta, rows if rows is not None else torch.empty(0), conics, colors, opacities)
        return plan.from_tiles(out.transpose(1, 2)), plan.from_tiles(T_out[..., None])

    @staticmethod
    def backward(ctx, v_render: Tensor, v_T: Tensor):
        means2d_meta, rows, conics, colors, opacities = ctx.saved_tensors
        plan: _Plan = ctx.plan
        rows = rows if ctx.has_rows else None
        dtype, device = colors.dtype, colors.device
        means2d = means2d_meta.reshape(-1, 2)
        if rows is not None:
            means2d = means2d[rows]
        M, D = colors.shape
        colors_t = colors.t()
        alpha_keep = _below(ALPHA_MIN, dtype)
        v_tiles = plan.to_tiles(v_render.to(dtype))  # [C * n_tiles, P, D]
        vT_tiles = plan.to_tiles(v_T.to(dtype))[..., 0]  # [C * n_tiles, P]
        v_means2d = torch.zeros((M, 2), dtype=dtype, device=device)
        v_abs = torch.zeros((M, 2), dtype=dtype, device=device) if ctx.absgrad else None
        v_conics = torch.zeros((M, 3), dtype=dtype, device=device)
        v_colors = torch.zeros((M, D), dtype=dtype, device=device)
        v_opac = torch.zeros((M,), dtype=dtype, device=device)
        for tiles, px, py, blocks, T_final in ctx.schedule:
            vC = v_tiles[tiles]  # [n, P, D]
            # carry = R: the loss "behind" the current Gaussian, sum_{j>k} w_j g_j + T_final dL/dT_final,
            # accumulated back to front (suffix sums: no division chain).
            carry = T_final * vT_tiles[tiles]
            for blk in reversed(blocks):
                def sel(x: Tensor, blk: _Block = blk) -> Tensor:
                    return x if blk.rows is None else x[blk.rows]

                gid, m, con, opac = _gather_block(plan, sel(tiles), blk.start, blk.size, means2d, conics, opacities)
                dx, dy, vis, alpha_raw, alpha = _alpha_block(
                    sel(px)[..., None], sel(py)[..., None], m, con, opac, alpha_keep
                )
                Tc, _, w = _transmittance(blk.T0, alpha)
                vC_b = sel(vC)
                col_g = colors_t[:, gid].permute(1, 0, 2)  # [n, D, B]
                g = torch.bmm(vC_b, col_g)  # [n, P, B]: dL/d(weight) = color . dL/dpixel
                wg = w * g
                suffix = wg.flip(-1).cumsum_(-1).flip(-1)  # inclusive suffix sums within the block
                carry_b = sel(carry)
                new_carry = carry_b + suffix[..., 0]
                carry = new_carry if blk.rows is None else carry.index_copy(0, blk.rows, new_carry)
                R = suffix.add_(carry_b[..., None]).sub_(wg)
                # dL/dalpha_k = T_k g_k - R_k / (1 - alpha_k); only for included, unclamped Gaussians.
                v_alpha = (Tc[..., :-1] * g).sub_(R.div_(torch.sub(1.0, alpha)))
                unclamped = torch.empty_like(alpha)
                torch.le(alpha_raw, ALPHA_MAX, out=unclamped)
                v_alpha.mul_(torch.sign(w)).mul_(unclamped)  # w > 0 exactly for the included ones
                vv = vis.mul_(v_alpha)  # dL/dopacity per pixel
                v_opac_b = vv.sum(1)  # [n, B]
                v_sigma = vv.mul_(-opac[:, None, :])
                vdx = v_sigma * dx
                vdy = v_sigma * dy
                a, b, c = con[..., 0], con[..., 1], con[..., 2]
                sx, sy = vdx.sum(1), vdy.sum(1)
                v_m = torch.stack([a * sx + b * sy, b * sx + c * sy], -1)  # dsigma/dmean = conic @ delta
                if v_abs is not None:
                    ax = torch.addcmul(b[:, None, :] * vdy, a[:, None, :], vdx).abs_().sum(1)
                    ay = torch.addcmul(b[:, None, :] * vdx, c[:, None, :], vdy).abs_().sum(1)
                    v_abs_b = torch.stack([ax, ay], -1)
                v_con = torch.stack([0.5 * (vdx * dx).sum(1), (vdx * dy).sum(1), 0.5 * vdy.mul_(dy).sum(1)], -1)
                v_col = torch.bmm(vC_b.transpose(1, 2), w).transpose(1, 2)  # [n, B, D]
                flat = gid.reshape(-1)
                v_means2d.index_add_(0, flat, v_m.reshape(-1, 2))
                v_conics.index_add_(0, flat, v_con.reshape(-1, 3))
                v_colors.index_add_(0, flat, v_col.reshape(-1, D))
                v_opac.index_add_(0, flat, v_opac_b.reshape(-1))
                if v_abs is not None:
                    v_abs.index_add_(0, flat, v_abs_b.reshape(-1, 2))
        if rows is not None:
            v_meta = torch.zeros_like(means2d_meta).reshape(-1, 2).index_add_(0, rows, v_means2d)
        else:
            v_meta = v_means2d
        if v_abs is not None:
            if rows is not None:
                v_abs = torch.zeros_like(means2d_meta).reshape(-1, 2).index_add_(0, rows, v_abs)
            means2d_meta.absgrad = v_abs.reshape(means2d_meta.shape)
        return v_meta.reshape(means2d_meta.shape), None, v_conics, v_colors, v_opac, None, None

# ----------------------------------------------------------------------------------------------------------------
# Gradient guard
# ----------------------------------------------------------------------------------------------------------------


class _FiniteGrad(torch.autograd.Function):
    """Identity whose backward zeroes the gradient rows that are not finite (last line of defence: invalid
    Gaussians already get exact zeros; this catches overflow in extreme but valid ones)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        if g.is_sparse:
            g = g.coalesce()
            vals = g.values()
            bad = ~torch.isfinite(vals).reshape(vals.shape[0], -1).all(1)
            vals = torch.where(bad.reshape((-1,) + (1,) * (vals.dim() - 1)), 0.0, vals)
            return torch.sparse_coo_tensor(g.indices(), vals, g.shape, is_coalesced=True)
        if g.dim() == 0:
            return torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
        bad = ~torch.isfinite(g).reshape(g.shape[0], -1).all(1)
        return torch.where(bad.reshape((-1,) + (1,) * (g.dim() - 1)), 0.0, g)


def _guard(x: Optional[Tensor]) -> Optional[Tensor]:
    return _FiniteGrad.apply(x) if x is not None and x.requires_grad else x


def _row_finite(x: Tensor, n_lead: int = 1) -> Tensor:
    return torch.isfinite(x).reshape(x.shape[:n_lead] + (-1,)).all(-1)


def rasterize_pairs(
    means2d: Tensor,  # [nnz, 2]
    conics: Tensor,  # [nnz, 3]
    colors: Tensor,  # [nnz, D]
    opacities: Tensor,  # [nnz]
    radii: Tensor,  # [nnz] int
    depths: Tensor,  # [nnz]
    camera_ids: Tensor,  # [nnz] int64
    n_cameras: int,
    width: int,
    height: int,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,  # [C, D]
) -> Tuple[Tensor, Tensor]:
    """Composite already projected, packed (camera, Gaussian) pairs: the twin of gsplat's `isect_tiles` +
    `isect_offset_encode` + `rasterize_to_pixels(..., packed=True)`.

    Differentiable w.r.t. means2d, conics, colors and opacities, each pair separately (no sum over cameras).
    Returns render_colors [C, H, W, D] and render_alphas [C, H, W, 1]."""
    plan = _Plan(means2d.detach(), radii.int(), depths.detach(), camera_ids.long(), n_cameras, width, height, tile_size)
    render, T_final = _RasterizeToPixels.apply(means2d, None, conics, colors, opacities, plan, False)
    if backgrounds is not None:
        render = render + T_final * backgrounds[:, None, None, :]
    return render, 1.0 - T_final


# ----------------------------------------------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------------------------------------------


def rasterization(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [(C,) N, D] or [(C,) N, K, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,  # [C, D]
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    channel_chunk: int = 32,
    distributed: bool = False,
    camera_model: str = "pinhole",
    covars: Optional[Tensor] = None,  # [N, 3, 3]
) -> Tuple[Tensor, Tensor, Dict]:
    """Rasterize N Gaussians into C images, as gsplat 1.4.0's `rasterization` (same arguments and defaults).

    Supported: packed True/False, render_mode RGB|D|ED|RGB+D|RGB+ED, rasterize_mode classic|antialiased,
    sh_degree None (colors [(C,) N, D]) or 0..4 (colors [(C,) N, K, 3]), backgrounds [C, D], absgrad,
    sparse_grad (packed only, as gsplat), radius_clip, covars [N, 3, 3] instead of quats/scales,
    camera_model pinhole|ortho. Unsupported (UnsupportedArgumentError): distributed=True, camera_model="fisheye",
    unknown modes, sh_degree > 4. `channel_chunk` only changes how gsplat batches channels, not the result.

    Returns:
        render_colors [C, H, W, X] (X = D, 1 or D+1 by render_mode), render_alphas [C, H, W, 1], meta with
        camera_ids, gaussian_ids (None when unpacked), radii [C, N] / [nnz] int32, means2d [C, N, 2] / [nnz, 2]
        (its .grad is the sum over pixels, .absgrad the sum of absolute per-pixel gradients when absgrad=True),
        depths, conics, opacities, tile_width, tile_height, tiles_per_gauss, isect_ids, flatten_ids,
        isect_offsets, width, height, tile_size, n_cameras.
    """
    # ---- arguments ------------------------------------------------------------------------------------------
    if distributed:
        raise UnsupportedArgumentError("cpu_raster.rasterization: distributed=True is not supported")
    if camera_model not in ("pinhole", "ortho"):
        raise UnsupportedArgumentError(
            f"cpu_raster.rasterization: camera_model={camera_model!r} is not supported (pinhole, ortho)")
    if render_mode not in _RENDER_MODES:
        raise UnsupportedArgumentError(
            f"cpu_raster.rasterization: render_mode={render_mode!r} is not one of {_RENDER_MODES}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise UnsupportedArgumentError(
            f"cpu_raster.rasterization: rasterize_mode={rasterize_mode!r} is not classic or antialiased")
    if sh_degree is not None and not (0 <= sh_degree <= 4):
        raise UnsupportedArgumentError(f"cpu_raster.rasterization: sh_degree={sh_degree} is not in 0..4")
    if tile_size < 1 or width < 1 or height < 1:
        raise UnsupportedArgumentError(f"cpu_raster.rasterization: bad image/tile size {width}x{height}/{tile_size}")
    N, C = means.shape[0], viewmats.shape[0]
    device, dtype = means.device, means.dtype

    def check(ok: bool, what: str) -> None:
        if not ok:
            raise ValueError(f"cpu_raster.rasterization: {what}")

    check(means.shape == (N, 3), f"means must be [N, 3], got {tuple(means.shape)}")
    if covars is None:
        check(quats.shape == (N, 4), f"quats must be [N, 4], got {tuple(quats.shape)}")
        check(scales.shape == (N, 3), f"scales must be [N, 3], got {tuple(scales.shape)}")
    else:
        check(covars.shape == (N, 3, 3), f"covars must be [N, 3, 3], got {tuple(covars.shape)}")
    check(opacities.shape == (N,), f"opacities must be [N], got {tuple(opacities.shape)}")
    check(viewmats.shape == (C, 4, 4), f"viewmats must be [C, 4, 4], got {tuple(viewmats.shape)}")
    check(Ks.shape == (C, 3, 3), f"Ks must be [C, 3, 3], got {tuple(Ks.shape)}")
    if sh_degree is None:
        check((colors.dim() == 2 and colors.shape[0] == N) or (colors.dim() == 3 and colors.shape[:2] == (C, N)),
              f"colors must be [N, D] or [C, N, D], got {tuple(colors.shape)}")
    else:
        check((colors.dim() == 3 and colors.shape[0] == N and colors.shape[2] == 3)
              or (colors.dim() == 4 and colors.shape[:2] == (C, N) and colors.shape[3] == 3),
              f"colors must be [N, K, 3] or [C, N, K, 3] SH coefficients, got {tuple(colors.shape)}")
        check((sh_degree + 1) ** 2 <= colors.shape[-2], f"sh_degree={sh_degree} needs {(sh_degree + 1) ** 2} bases")
    per_camera_colors = colors.dim() == (4 if sh_degree is not None else 3)
    use_sparse = sparse_grad and packed
    Ks = Ks.detach()  # gsplat is not differentiable w.r.t. the intrinsics
    means, quats, scales, opacities, colors, covars = map(_guard, (means, quats, scales, opacities, colors, covars))
    if covars is not None:
        # gsplat keeps the upper triangle of covars: symmetrise it the same way.
        tri = torch.triu(covars)
        covars = tri + torch.triu(covars, 1).transpose(-1, -2)

    # ---- pass 1 (no grad): which (camera, Gaussian) pairs are valid ---------------------------------------------
    with torch.no_grad():
        ok = _row_finite(means) & torch.isfinite(opacities)
        ok &= _row_finite(colors, 2 if per_camera_colors else 1).all(0) if per_camera_colors else _row_finite(colors)
        if covars is None:
            qn = (quats * quats).sum(-1)
            ok &= _row_finite(quats) & _row_finite(scales) & torch.isfinite(qn) & (qn > 0)
            safe_q = torch.where(ok[:, None], quats, torch.tensor([1.0, 0, 0, 0], dtype=dtype, device=device))
            safe_s = torch.where(ok[:, None], scales, 0.0)
            cov_w = quat_scale_to_covar(safe_q, safe_s)
        else:
            ok &= _row_finite(covars)
            cov_w = torch.where(ok[:, None, None], covars, 0.0)
        safe_means = torch.where(ok[:, None], means, 0.0)
        proj = project(safe_means[None], cov_w[None], viewmats[:, None], Ks[:, None], width, height, eps2d,
                        camera_model == "ortho", radius_floor=0.1 if packed else 0.01)
        z, radius, m2 = proj["depths"], proj["radius"], proj["means2d"]
        valid = ok[None, :] & _row_finite(viewmats)[:, None]
        valid &= (z >= near_plane) & (z <= far_plane) & (proj["det"] > 0)
        valid &= _row_finite(m2, 2) & _row_finite(proj["conics"], 2) & torch.isfinite(proj["compensations"])
        valid &= torch.isfinite(radius) & (radius < _INT32_MAX) & (radius > radius_clip)
        valid &= (m2[..., 0] + radius > 0) & (m2[..., 0] - radius < width)
        valid &= (m2[..., 1] + radius > 0) & (m2[..., 1] - radius < height)
        # The quadratic form must stay finite at every pixel of every touched tile (|d| <= radius + image + tile).
        reach = radius + max(width, height) + tile_size
        big = torch.finfo(dtype).max / 16
        valid &= proj["conics"].abs().amax(-1).nan_to_num(math.inf) * reach * reach < big
        cids, gids = torch.nonzero(valid, as_tuple=True)  # row-major: gsplat's (camera, Gaussian) order
        radii_valid = radius[cids, gids].int()

    # ---- pass 2 (differentiable) on the valid pairs ------------------------------------------------------------
    def gather(x: Tensor) -> Tensor:
        if use_sparse and x.dim() == 2:
            return F.embedding(gids, x, sparse=True)
        return x[gids]

    means_v = gather(means)
    cov_v = quat_scale_to_covar(gather(quats), gather(scales)) if covars is None else covars[gids]
    proj = project(means_v, cov_v, viewmats[cids], Ks[cids], width, height, eps2d, camera_model == "ortho")
    means2d_v, depths_v, conics_v = proj["means2d"], proj["depths"], proj["conics"]
    opac_v = opacities[gids]
    if rasterize_mode == "antialiased":
        opac_v = opac_v * proj["compensations"]

    if sh_degree is None:
        colors_v = colors[cids, gids] if per_camera_colors else colors[gids]
    else:
        campos = torch.inverse(viewmats)[:, :3, 3]  # [C, 3], differentiable like gsplat's torch.inverse
        dirs = means_v - campos[cids]
        coeffs = colors[cids, gids] if per_camera_colors else colors[gids]
        colors_v = torch.clamp_min(sh_to_color(sh_degree, dirs, coeffs) + 0.5, 0.0)
    if render_mode in ("RGB+D", "RGB+ED"):
        colors_v = torch.cat([colors_v, depths_v[:, None]], -1)
    elif render_mode in ("D", "ED"):
        colors_v = depths_v[:, None]
    if backgrounds is not None:
        check(backgrounds.shape[0] == C, f"backgrounds must be [C, D], got {tuple(backgrounds.shape)}")
        if render_mode in ("RGB+D", "RGB+ED"):
            backgrounds = torch.cat([backgrounds, torch.zeros_like(backgrounds[:, :1])], -1)
        elif render_mode in ("D", "ED"):
            backgrounds = torch.zeros_like(backgrounds[:, :1])
        check(backgrounds.shape[-1] == colors_v.shape[-1], "backgrounds channels differ from colors")

    # ---- tiles and compositing ---------------------------------------------------------------------------------
    plan = _Plan(means2d_v.detach(), radii_valid, depths_v.detach(), cids, C, width, height, tile_size)
    if packed:
        means2d_meta, rows = means2d_v, None
    else:
        means2d_meta = torch.zeros((C, N, 2), dtype=dtype, device=device).index_put((cids, gids), means2d_v)
        rows = cids * N + gids
    render, T_final = _RasterizeToPixels.apply(means2d_meta, rows, conics_v, colors_v, opac_v, plan, absgrad)
    alphas = 1.0 - T_final
    if backgrounds is not None:
        render = render + T_final * backgrounds[:, None, None, :]
    if render_mode in ("ED", "RGB+ED"):
        render = torch.cat([render[..., :-1], render[..., -1:] / alphas.clamp(min=1e-10)], -1)

    # ---- meta, in gsplat's layout ------------------------------------------------------------------------------
    flatten_ids = plan.flatten if packed else rows[plan.flatten]
    tile_bits = int(math.floor(math.log2(plan.n_tiles))) + 1
    local_tile = plan.gtile_sorted % plan.n_tiles
    isect_ids = ((plan.gtile_sorted // plan.n_tiles) << (32 + tile_bits)) | (local_tile << 32)
    isect_ids = isect_ids | (depths_v.detach().float().contiguous().view(torch.int32).long() & 0xFFFFFFFF)[plan.flatten]
    if packed:
        radii = radii_valid
        depths_m, conics_m, opac_m = depths_v, conics_v, opac_v
        tiles_per_gauss = plan.tiles_per_gauss
        camera_ids, gaussian_ids = cids, gids
    else:
        def dense(x: Tensor, fill: float = 0.0) -> Tensor:
            out = torch.full((C, N) + x.shape[1:], fill, dtype=x.dtype, device=device)
            return out.index_put((cids, gids), x)

        radii = dense(radii_valid)
        depths_m, conics_m, opac_m = dense(depths_v), dense(conics_v), dense(opac_v)
        tiles_per_gauss = dense(plan.tiles_per_gauss)
        camera_ids, gaussian_ids = None, None
    meta = {
        "camera_ids": camera_ids,
        "gaussian_ids": gaussian_ids,
        "radii": radii,
        "means2d": means2d_meta,
        "depths": depths_m,
        "conics": conics_m,
        "opacities": opac_m,
        "tile_width": plan.tile_width,
        "tile_height": plan.tile_height,
        "tiles_per_gauss": tiles_per_gauss,
        "isect_ids": isect_ids,
        "flatten_ids": flatten_ids.int(),
        "isect_offsets": plan.tile_offsets.int().reshape(C, plan.tile_height, plan.tile_width),
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_cameras": C,
    }
    return render, alphas, meta
