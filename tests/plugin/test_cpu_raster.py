"""hpgs_ns.cpu_raster: the pure-PyTorch twin of gsplat 1.4.0's `rasterization`.

The specification is `reference_rasterization` below: projection through gsplat's own pure-torch helpers
(`gsplat.cuda._torch_impl`, which never touch CUDA), then a slow per-pixel front-to-back loop written straight from
gsplat's CUDA kernel, differentiated by autograd. The fast module must agree with it to float64 round-off, images and
every gradient (absgrad included); gradients are also checked against finite differences. No test here is timed.
"""

from __future__ import annotations

import math
from typing import Dict

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hpgs_ns.cpu_raster import UnsupportedArgumentError, rasterization

F64 = torch.float64


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """These renders are tiny: one intra-op thread avoids OpenMP/MKL hand-offs that dominate them (and that turn
    very slow when the 2 cores are shared), and keeps the suite's time predictable."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# ----------------------------------------------------------------------------------------------------------------
# The specification: a slow per-pixel reference
# ----------------------------------------------------------------------------------------------------------------


class _GsplatCompensation(torch.autograd.Function):
    """sqrt(max(x, 0)), differentiated as gsplat's CUDA add_blur_vjp does: 0.5 / (sqrt(x) + 1e-6)."""

    @staticmethod
    def forward(ctx, x):
        y = torch.sqrt(torch.clamp(x, min=0.0))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, g):
        (y,) = ctx.saved_tensors
        return g * 0.5 / (y + 1e-6)


def reference_rasterization(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=0.01, far_plane=1e10,
    radius_clip=0.0, eps2d=0.3, sh_degree=None, tile_size=16, backgrounds=None, render_mode="RGB",
    rasterize_mode="classic", packed=False,
):
    """gsplat 1.4.0's rasterization, one pixel at a time (vectorised over pixels, a Python loop over Gaussians).

    Returns (colors [C,H,W,X], alphas [C,H,W,1], info) where info["means2d"] [C,N,2] retains its grad and
    info["means2d_pp"] [C,HW,N,2] collects per-pixel means2d gradients (for absgrad)."""
    from gsplat.cuda._torch_impl import _persp_proj, _quat_scale_to_covar_preci, _spherical_harmonics, _world_to_cam

    C = viewmats.shape[0]
    dtype = means.dtype
    covars, _ = _quat_scale_to_covar_preci(quats, scales, True, False)
    means_c, covars_c = _world_to_cam(means, covars, viewmats)
    means2d, cov2d = _persp_proj(means_c, covars_c, Ks, width, height)
    if means2d.requires_grad:
        means2d.retain_grad()
    det_orig = cov2d[..., 0, 0] * cov2d[..., 1, 1] - cov2d[..., 0, 1] * cov2d[..., 1, 0]
    cov2d = cov2d + eps2d * torch.eye(2, dtype=dtype)
    a, b, c = cov2d[..., 0, 0], cov2d[..., 0, 1], cov2d[..., 1, 1]
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], -1)
    depths = means_c[..., 2]
    with torch.no_grad():
        half = 0.5 * (a + c)
        # gsplat 1.4.0 floors b^2 - det at 0.01 in its unpacked projection kernel and at 0.1 in the packed one
        floor = 0.1 if packed else 0.01
        radius = torch.ceil(3 * torch.sqrt(half + torch.sqrt(torch.clamp(half * half - det, min=floor))))
        m2 = means2d
        valid = (depths >= near_plane) & (depths <= far_plane) & (det > 0) & (radius > radius_clip)
        valid &= (m2[..., 0] + radius > 0) & (m2[..., 0] - radius < width)
        valid &= (m2[..., 1] + radius > 0) & (m2[..., 1] - radius < height)
    if sh_degree is not None:
        campos = torch.inverse(viewmats)[:, :3, 3]
        dirs = means[None] - campos[:, None]
        coeffs = colors.expand(C, -1, -1, -1) if colors.dim() == 3 else colors
        cols = torch.clamp_min(_spherical_harmonics(sh_degree, dirs, coeffs) + 0.5, 0.0)
    else:
        cols = colors.expand(C, -1, -1) if colors.dim() == 2 else colors
    if render_mode in ("RGB+D", "RGB+ED"):
        cols = torch.cat([cols, depths[..., None]], -1)
    elif render_mode in ("D", "ED"):
        cols = depths[..., None]
    opac = opacities[None].expand(C, -1)
    if rasterize_mode == "antialiased":
        opac = opac * _GsplatCompensation.apply(det_orig / det)

    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    px, py = xs.flatten().to(dtype) + 0.5, ys.flatten().to(dtype) + 0.5
    tile_x, tile_y = xs.flatten() // tile_size, ys.flatten() // tile_size
    tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
    # One copy of means2d per pixel: autograd then gives per-pixel gradients (absgrad sums their magnitudes).
    m2_pp = means2d.detach()[:, None].repeat(1, px.shape[0], 1, 1).requires_grad_()
    m2_use = means2d[:, None] + (m2_pp - m2_pp.detach())
    images, alphas = [], []
    for ci in range(C):
        T = torch.ones_like(px)
        done = torch.zeros_like(px, dtype=torch.bool)
        out = torch.zeros(px.shape[0], cols.shape[-1], dtype=dtype)
        for g in torch.sort(depths[ci].detach(), stable=True).indices.tolist():  # front to back
            if not valid[ci, g]:
                continue
            # Tiles touched by the square of half-side radius (gsplat's isect_tiles rule).
            r = float(radius[ci, g]) / tile_size
            mx, my = (float(v) / tile_size for v in means2d[ci, g].detach())
            x0, x1 = min(max(math.floor(mx - r), 0), tw), min(max(math.ceil(mx + r), 0), tw)
            y0, y1 = min(max(math.floor(my - r), 0), th), min(max(math.ceil(my + r), 0), th)
            touched = (tile_x >= x0) & (tile_x < x1) & (tile_y >= y0) & (tile_y < y1)
            dx = m2_use[ci, :, g, 0] - px
            dy = m2_use[ci, :, g, 1] - py
            ca, cb, cc = conics[ci, g]
            sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            alpha = torch.clamp_max(opac[ci, g] * torch.exp(-sigma), 0.999)
            use = touched & ~done & (sigma >= 0) & (alpha >= 1.0 / 255.0)
            next_T = T * (1 - alpha)
            stop = use & (next_T <= 1e-4)  # exclusive: this Gaussian is not drawn
            done = done | stop
            use = use & ~stop
            out = out + torch.where(use[:, None], (alpha * T)[:, None] * cols[ci, g][None], 0.0)
            T = torch.where(use, next_T, T)
        if backgrounds is not None:
            bg = backgrounds[ci]
            if render_mode in ("RGB+D", "RGB+ED"):
                bg = torch.cat([bg, bg.new_zeros(1)])
            elif render_mode in ("D", "ED"):
                bg = bg.new_zeros(1)
            out = out + T[:, None] * bg
        images.append(out.reshape(height, width, -1))
        alphas.append((1 - T).reshape(height, width, 1))
    img, alp = torch.stack(images), torch.stack(alphas)
    if render_mode in ("ED", "RGB+ED"):
        img = torch.cat([img[..., :-1], img[..., -1:] / alp.clamp(min=1e-10)], -1)
    info = {"means2d": means2d, "means2d_pp": m2_pp, "radii": torch.where(valid, radius, 0).int(), "depths": depths}
    return img, alp, info


# ----------------------------------------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------------------------------------


def look_at(eye, target=(0.0, 0.0, 0.0), dtype=F64) -> torch.Tensor:
    """World-to-camera [4,4] (OpenCV: x right, y down, z forward) for a camera at eye looking at target."""
    eye, target = torch.tensor(eye, dtype=dtype), torch.tensor(target, dtype=dtype)
    fwd = (target - eye) / (target - eye).norm()
    up = torch.tensor([0.0, -1.0, 0.0], dtype=dtype)
    right = torch.linalg.cross(fwd, up)
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])  # rows: camera axes in world coordinates
    V = torch.eye(4, dtype=dtype)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V


def make_scene(n=30, seed=0, dtype=F64, width=40, height=36, n_cameras=1, sh_degree=None, spread=0.7,
               scale_range=(0.03, 0.2), D=3) -> Dict:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * spread
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    lo, hi = scale_range
    scales = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=dtype)
    if sh_degree is None:
        colors = torch.rand(n, D, generator=g, dtype=dtype)
    else:
        colors = 0.4 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=dtype)
    eyes = [(0.3, -0.2, -3.0), (2.2, 0.4, -2.2), (-2.0, -0.6, -2.4)]
    viewmats = torch.stack([look_at(eyes[i % 3], dtype=dtype) for i in range(n_cameras)])
    f = 0.9 * width
    Ks = torch.tensor([[f, 0, width / 2 + 0.3], [0, f * 1.05, height / 2 - 0.2], [0, 0, 1]], dtype=dtype)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats,
                Ks=Ks[None].repeat(n_cameras, 1, 1), width=width, height=height, sh_degree=sh_degree)


PARAMS = ("means", "quats", "scales", "opacities", "colors")


def loss_weights(render: torch.Tensor, alphas: torch.Tensor):
    """Fixed, sign-changing weights: a loss sensitive to every pixel and channel."""
    wr = torch.cos(torch.arange(render.numel(), dtype=render.dtype) * 0.37).reshape(render.shape)
    wa = torch.sin(torch.arange(alphas.numel(), dtype=alphas.dtype) * 0.11 + 0.5).reshape(alphas.shape)
    return wr, wa


def render_and_grad(fn, scene: Dict, grad_of=PARAMS, **kw):
    s = {k: (v.detach().clone().requires_grad_() if k in grad_of else v) for k, v in scene.items()}
    render, alphas, meta = fn(**s, **kw)
    if meta["means2d"].requires_grad:
        meta["means2d"].retain_grad()
    wr, wa = loss_weights(render, alphas)
    loss = (render * wr).sum() + (alphas * wa).sum()
    if loss.requires_grad:  # (the reference's image is a constant when no Gaussian is visible)
        loss.backward()
    return render, alphas, meta, {k: s[k].grad for k in grad_of}


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


# ----------------------------------------------------------------------------------------------------------------
# Agreement with the specification (float64)
# ----------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "case",
    [
        dict(),
        dict(packed=True),
        dict(render_mode="RGB+ED", backgrounds=True),
        dict(render_mode="D"),
        dict(render_mode="ED", n_cameras=2),
        dict(render_mode="RGB+D", rasterize_mode="antialiased"),
        dict(sh_degree=3, n_cameras=2, backgrounds=True),
        dict(sh_degree=1, rasterize_mode="antialiased", packed=True),
        dict(per_camera_colors=True, n_cameras=2, D=5, backgrounds=True),  # [C, N, D] features, D != 3
        dict(per_camera_colors=True, n_cameras=2, sh_degree=2, packed=True),  # [C, N, K, 3] SH
    ],
    ids=lambda c: ",".join(f"{k}={v}" for k, v in c.items()) or "default",
)
def test_matches_reference_images_and_gradients(case):
    case = dict(case)
    C = case.pop("n_cameras", 1)
    scene = make_scene(n=36, seed=3, n_cameras=C, sh_degree=case.pop("sh_degree", None), D=case.pop("D", 3))
    if case.pop("per_camera_colors", False):
        scene["colors"] = scene["colors"][None].repeat((C,) + (1,) * scene["colors"].dim()) * torch.linspace(
            0.5, 1.0, C, dtype=F64).reshape((C,) + (1,) * scene["colors"].dim())
    if case.pop("backgrounds", False):
        D = 3 if scene["sh_degree"] is not None else scene["colors"].shape[-1]
        scene["backgrounds"] = torch.linspace(0.1, 0.9, C * D, dtype=F64).reshape(C, D)
    packed = case.pop("packed", False)
    grad_of = PARAMS + (("backgrounds",) if "backgrounds" in scene else ())
    r_ref, a_ref, m_ref, g_ref = render_and_grad(reference_rasterization, scene, grad_of, packed=packed, **case)
    r, a, meta, g = render_and_grad(rasterization, scene, grad_of, packed=packed, absgrad=True, **case)
    assert r.shape == r_ref.shape and a.shape == a_ref.shape
    assert (a_ref > 0.5).any(), "the scene must cover part of the image"
    torch.testing.assert_close(r, r_ref, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(a, a_ref, rtol=1e-9, atol=1e-10)
    tol = 1e-9
    for k in grad_of:
        if k == "colors" and case.get("render_mode") in ("D", "ED"):
            assert g[k] is None and g_ref[k] is None  # colours are not rendered
            continue
        assert g_ref[k].abs().sum() > 0, k
        assert rel(g[k], g_ref[k]) < tol, (k, rel(g[k], g_ref[k]))
    # means2d: grad is the sum over pixels, absgrad the sum of per-pixel magnitudes, as gsplat's backward
    ref_grad2d, ref_abs2d = m_ref["means2d"].grad, m_ref["means2d_pp"].grad.abs().sum(1)
    radii = m_ref["radii"]
    if packed:
        cid, gid = meta["camera_ids"], meta["gaussian_ids"]
        ref_grad2d, ref_abs2d, radii = ref_grad2d[cid, gid], ref_abs2d[cid, gid], radii[cid, gid]
    assert torch.equal(meta["radii"], radii)
    assert rel(meta["means2d"].grad, ref_grad2d) < tol
    assert rel(meta["means2d"].absgrad, ref_abs2d) < tol
    assert (meta["means2d"].absgrad >= meta["means2d"].grad.abs() - 1e-12).all()


def test_gradients_match_finite_differences():
    """torch.autograd.gradcheck (central differences, float64) for every differentiable input at once."""
    scene = make_scene(n=6, seed=11, width=20, height=18, sh_degree=1, scale_range=(0.08, 0.3), spread=0.4)
    bg = torch.tensor([[0.3, 0.6, 0.1]], dtype=F64)
    names = PARAMS + ("viewmats", "backgrounds")
    inputs = [scene[k].clone().requires_grad_() for k in PARAMS] + [
        scene["viewmats"].clone().requires_grad_(), bg.clone().requires_grad_()]

    def fn(means, quats, scales, opacities, colors, viewmats, backgrounds):
        r, a, _ = rasterization(means, quats, scales, opacities, colors, viewmats, scene["Ks"], scene["width"],
                                scene["height"], sh_degree=1, backgrounds=backgrounds, render_mode="RGB+ED",
                                rasterize_mode="antialiased", packed=False)
        return r, a

    assert len(inputs) == len(names)
    _, alphas = fn(*inputs)
    assert float(alphas.max()) > 0.5 and float((alphas > 1 / 255).float().mean()) > 0.2  # a non-trivial Jacobian
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


# ----------------------------------------------------------------------------------------------------------------
# Conventions, stated with numbers
# ----------------------------------------------------------------------------------------------------------------


def one_gaussian(mean=(0.0, 0.0, 2.0), scale=0.05, opacity=0.8, color=(1.0, 0.5, 0.25), width=32, height=32, f=32.0,
                c=None):
    """One isotropic Gaussian, camera at the origin looking along +z; principal point c (default: the image centre
    plus half a pixel, so that a mean on the axis projects onto a pixel centre)."""
    cx, cy = c if c is not None else (width / 2 + 0.5, height / 2 + 0.5)
    return dict(
        means=torch.tensor([mean], dtype=F64), quats=torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
        scales=torch.full((1, 3), scale, dtype=F64), opacities=torch.tensor([opacity], dtype=F64),
        colors=torch.tensor([color], dtype=F64), viewmats=torch.eye(4, dtype=F64)[None],
        Ks=torch.tensor([[[f, 0, cx], [0, f, cy], [0, 0, 1]]], dtype=F64), width=width, height=height,
    )


def test_single_gaussian_formula_radius_and_tile_shading():
    f, z, x, y, sc = 32.0, 2.0, 0.1, -0.05, 0.05
    s = one_gaussian(mean=(x, y, z), scale=sc, c=(16.0, 16.0))
    r, a, meta = rasterization(**s, packed=False)
    # EWA: cov2d = J (s^2 I) J^T + eps2d I with J = [[f/z, 0, -f x/z^2], [0, f/z, -f y/z^2]]; mean2d = f x / z + c
    J = torch.tensor([[f / z, 0, -f * x / z**2], [0, f / z, -f * y / z**2]], dtype=F64)
    cov = sc**2 * J @ J.T + 0.3 * torch.eye(2, dtype=F64)
    conic = torch.linalg.inv(cov)
    mx, my = f * x / z + 16, f * y / z + 16
    torch.testing.assert_close(meta["means2d"][0, 0], torch.tensor([mx, my], dtype=F64))
    torch.testing.assert_close(meta["conics"][0, 0], torch.stack([conic[0, 0], conic[0, 1], conic[1, 1]]))
    # radius = ceil(3 sqrt(largest eigenvalue)), with gsplat's floor of 0.01 under the square root's argument
    b, det = 0.5 * float(cov.trace()), float(torch.linalg.det(cov))
    assert meta["radii"][0, 0] == math.ceil(3 * math.sqrt(b + math.sqrt(max(0.01, b * b - det)))) == 4
    ys, xs = torch.meshgrid(torch.arange(32, dtype=F64) + 0.5, torch.arange(32, dtype=F64) + 0.5, indexing="ij")
    dx, dy = mx - xs, my - ys
    sigma = 0.5 * (conic[0, 0] * dx * dx + conic[1, 1] * dy * dy) + conic[0, 1] * dx * dy
    alpha = torch.clamp_max(0.8 * torch.exp(-sigma), 0.999)
    alpha = torch.where(alpha >= 1 / 255, alpha, 0.0)
    # the box [mx - 4, mx + 4] touches all four tiles of the 32x32 image, so every pixel is shaded
    assert int(meta["tiles_per_gauss"][0, 0]) == 4
    torch.testing.assert_close(a[0, ..., 0], alpha)
    torch.testing.assert_close(r[0], alpha[..., None] * torch.tensor([1.0, 0.5, 0.25], dtype=F64))


def test_tiles_not_touched_are_not_shaded():
    # cov2d = 15.6 + 0.3 = 15.9 px^2, radius = ceil(3 sqrt(15.9 + 0.1)) = 12; mean2d at (3.99, 3.99): the box ends at
    # 15.99, inside tile (0, 0). The neighbouring tile stays black although the Gaussian's alpha at its first pixel
    # centre (16.5, 4.5) is above 1/255: gsplat shades a Gaussian only in the tiles its box touches.
    f, z = 64.0, 2.0
    scale = math.sqrt(15.6) * z / f
    # on the optical axis (no perspective skew of the covariance), principal point at (3.99, 3.99)
    s = one_gaussian(mean=(0.0, 0.0, z), scale=scale, opacity=0.99, width=64, height=64, f=f, c=(3.99, 3.99))
    r, a, meta = rasterization(**s, packed=False)  # (packed: gsplat's radius floor 0.1 would give 13)
    assert int(meta["radii"][0, 0]) == 12 and int(meta["tiles_per_gauss"][0, 0]) == 1
    would_be = 0.99 * math.exp(-0.5 * ((16.5 - 3.99) ** 2 + (4.5 - 3.99) ** 2) / 15.9)
    assert would_be > 1 / 255
    assert float(a[0, :16, :16].max()) > 0.5 and float(a[0, 4, 15]) > 1 / 255
    assert float(a[0, :, 16:].max()) == 0.0 and float(a[0, 16:, :].max()) == 0.0


def test_alpha_clamp_and_exclusive_stop():
    # Opacity 1 at the centre clamps to 0.999; a second identical Gaussian behind it would bring T to 1e-6 <= 1e-4,
    # so it is not drawn at all (exclusive stop): alpha stays 0.999 and its colour never shows.
    s = one_gaussian(opacity=1.0, color=(1.0, 0.0, 0.0), width=16, height=16, f=16.0, c=(8.5, 8.5))
    back = one_gaussian(mean=(0.0, 0.0, 2.5), opacity=1.0, color=(0.0, 1.0, 0.0), width=16, height=16, f=16.0)
    both = {k: torch.cat([s[k], back[k]]) if k in PARAMS else s[k] for k in s}
    r, a, _ = rasterization(**both)
    centre = (8, 8)
    assert float(a[0, centre[0], centre[1], 0]) == pytest.approx(0.999, abs=1e-12)
    assert float(r[0, centre[0], centre[1], 1]) == 0.0  # green never composited at the centre
    # Three Gaussians of alpha 0.9 in a row: T goes 1 -> 0.1 -> 0.01 -> 0.001 (> 1e-4): all three drawn.
    s3 = {k: torch.cat([one_gaussian(mean=(0, 0, 2 + 0.1 * i), opacity=0.9, scale=1.0)[k] for i in range(3)])
          if k in PARAMS else s[k] for k in s}
    _, a3, _ = rasterization(**s3)
    assert float(a3[0, 8, 8, 0]) > 0.9989


def test_depth_order_and_background_and_modes():
    s = one_gaussian(opacity=0.6, color=(1.0, 0.0, 0.0), scale=1.0, width=16, height=16, f=16.0)
    back = one_gaussian(mean=(0.0, 0.0, 4.0), opacity=0.5, color=(0.0, 1.0, 0.0), scale=2.0, width=16, height=16,
                        f=16.0)
    # back first in the arrays: the rasterizer must still composite front (z=2) over back (z=4)
    both = {k: torch.cat([back[k], s[k]]) if k in PARAMS else s[k] for k in s}
    bg = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    r, a, _ = rasterization(**both, backgrounds=bg, render_mode="RGB+ED")
    px = r[0, 8, 8]
    assert float(px[0]) > float(px[1]) > 0  # red in front of green
    T = 1 - float(a[0, 8, 8, 0])
    assert float(px[2]) == pytest.approx(T * 1.0, rel=1e-12)  # background weighted by the final transmittance
    # "ED" = accumulated depth / alpha; "D" = accumulated depth; depth channel has no background
    rd, ad, _ = rasterization(**both, backgrounds=bg, render_mode="D")
    red, _, _ = rasterization(**both, backgrounds=bg, render_mode="ED")
    torch.testing.assert_close(red[..., 0], rd[..., 0] / ad[..., 0].clamp_min(1e-10))
    torch.testing.assert_close(r[..., 3], red[..., 0])
    # exactly: alpha_front = 0.6 at the centre, alpha_back = 0.5: ED = (0.6 * 2 + 0.4 * 0.5 * 4) / (1 - 0.4 * 0.5)
    assert float(red[0, 8, 8, 0]) == pytest.approx((0.6 * 2 + 0.4 * 0.5 * 4) / 0.8, rel=1e-12)


def test_near_far_culling_and_radius_clip():
    s = one_gaussian(scale=0.1)
    near = {k: torch.cat([s[k], one_gaussian(mean=(0, 0, 0.005))[k], one_gaussian(mean=(0, 0, -1.0))[k],
                          one_gaussian(mean=(0, 0, 50.0))[k]]) if k in PARAMS else s[k] for k in s}
    _, _, meta = rasterization(**near, far_plane=20.0, packed=False)
    assert meta["radii"][0].tolist()[1:] == [0, 0, 0] and meta["radii"][0, 0] > 0
    _, _, meta = rasterization(**near, far_plane=20.0, radius_clip=100.0, packed=False)
    assert int(meta["radii"].max()) == 0


# ----------------------------------------------------------------------------------------------------------------
# Meta, packed / unpacked, absgrad, strategy
# ----------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("packed", [False, True])
def test_meta_keys_and_shapes(packed):
    scene = make_scene(n=25, seed=1, n_cameras=2, dtype=torch.float32)
    r, a, meta = rasterization(**scene, packed=packed, render_mode="RGB+ED")
    C, N, H, W = 2, 25, scene["height"], scene["width"]
    assert r.shape == (C, H, W, 4) and a.shape == (C, H, W, 1) and r.dtype == torch.float32
    for key in ("camera_ids", "gaussian_ids", "radii", "means2d", "depths", "conics", "opacities", "tile_width",
                "tile_height", "tiles_per_gauss", "isect_ids", "flatten_ids", "isect_offsets", "width", "height",
                "tile_size", "n_cameras"):
        assert key in meta, key
    assert (meta["width"], meta["height"], meta["n_cameras"], meta["tile_size"]) == (W, H, C, 16)
    assert (meta["tile_width"], meta["tile_height"]) == (3, 3)
    assert meta["radii"].dtype == torch.int32 and meta["isect_offsets"].shape == (C, 3, 3)
    if packed:
        nnz = meta["gaussian_ids"].shape[0]
        assert meta["means2d"].shape == (nnz, 2) and meta["radii"].shape == (nnz,) and (meta["radii"] > 0).all()
        assert meta["camera_ids"].shape == (nnz,) and meta["depths"].shape == (nnz,)
    else:
        assert meta["gaussian_ids"] is None and meta["camera_ids"] is None
        assert meta["means2d"].shape == (C, N, 2) and meta["radii"].shape == (C, N)
        assert meta["conics"].shape == (C, N, 3) and meta["depths"].shape == (C, N)
    assert int(meta["tiles_per_gauss"].sum()) == meta["isect_ids"].shape[0] == meta["flatten_ids"].shape[0]


def test_packed_and_unpacked_layouts_agree():
    """Same pairs, same projected values; radii differ only by gsplat's packed/unpacked radius floor."""
    scene = make_scene(n=40, seed=5, n_cameras=2, sh_degree=2)
    out = {p: render_and_grad(rasterization, scene, packed=p, absgrad=True, render_mode="RGB+D") for p in (0, 1)}
    (r0, _, m0, g0), (r1, _, m1, g1) = out[0], out[1]
    cid, gid = m1["camera_ids"], m1["gaussian_ids"]
    assert torch.equal(torch.nonzero(m0["radii"] > 0, as_tuple=True)[0], cid)  # (camera, Gaussian) order
    assert torch.equal(torch.nonzero(m0["radii"] > 0, as_tuple=True)[1], gid)
    assert (m1["radii"] >= m0["radii"][cid, gid]).all()  # floor 0.1 >= 0.01
    for key in ("means2d", "depths", "conics", "opacities"):
        torch.testing.assert_close(m0[key][cid, gid], m1[key], rtol=0, atol=0)
    # a slightly larger box can only add far-tail pixels: the images agree closely
    assert float((r0 - r1).abs().max()) < 0.05 and float((r0 - r1).abs().mean()) < 1e-3
    for k in PARAMS:
        assert rel(g1[k], g0[k]) < 0.05, k
    assert float(m0["means2d"].absgrad[m0["radii"] == 0].abs().sum()) == 0.0
    # With both floors inactive (b^2 - det >= 0.1 for every pair: strongly anisotropic), the results are identical.
    aniso = dict(scene, scales=scene["scales"] * torch.tensor([4.0, 0.3, 0.3], dtype=F64))
    out = {p: render_and_grad(rasterization, aniso, packed=p, absgrad=True) for p in (0, 1)}
    (r0, _, m0, g0), (r1, _, m1, g1) = out[0], out[1]
    cid, gid = m1["camera_ids"], m1["gaussian_ids"]
    assert torch.equal(m1["radii"], m0["radii"][cid, gid])
    torch.testing.assert_close(r0, r1, rtol=0, atol=1e-13)
    for k in PARAMS:
        torch.testing.assert_close(g0[k], g1[k], rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(m0["means2d"].absgrad[cid, gid], m1["means2d"].absgrad)


def test_sparse_grad_packed():
    scene = make_scene(n=20, seed=2)
    _, _, _, dense = render_and_grad(rasterization, scene, packed=True)
    _, _, _, sparse = render_and_grad(rasterization, scene, packed=True, sparse_grad=True)
    for k in ("means", "quats", "scales"):
        assert sparse[k].is_sparse
        torch.testing.assert_close(sparse[k].to_dense(), dense[k])


def test_default_strategy_reads_absgrad_like_gsplat():
    """gsplat's DefaultStrategy (splatfacto's) runs on our meta: grad2d accumulates |absgrad| normalised."""
    from gsplat.strategy import DefaultStrategy

    scene = make_scene(n=30, seed=4, dtype=torch.float32)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(scene[k].clone()) for k in PARAMS})
    optimizers = {k: torch.optim.Adam([params[k]], lr=1e-3) for k in PARAMS}
    strategy = DefaultStrategy(absgrad=True, verbose=False)
    state = strategy.initialize_state(scene_scale=1.0)
    r, a, info = rasterization(params["means"], params["quats"], params["scales"], params["opacities"],
                               params["colors"], scene["viewmats"], scene["Ks"], scene["width"], scene["height"],
                               packed=False, absgrad=True, render_mode="RGB+ED", tile_size=16)
    strategy.step_pre_backward(params, optimizers, state, step=0, info=info)
    (r[..., :3].sum() + a.sum()).backward()
    strategy.step_post_backward(params, optimizers, state, step=0, info=info, packed=False)
    g = info["means2d"].absgrad.clone()
    g[..., 0] *= scene["width"] / 2.0
    g[..., 1] *= scene["height"] / 2.0
    sel = info["radii"][0] > 0
    expected = torch.zeros(30).index_add_(0, torch.nonzero(sel).flatten(), g[0][sel].norm(dim=-1))
    torch.testing.assert_close(state["grad2d"], expected)
    assert torch.equal(state["count"], sel.float())
    assert float(info["means2d"].grad.abs().sum()) > 0


# ----------------------------------------------------------------------------------------------------------------
# Arguments
# ----------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kw",
    [dict(distributed=True), dict(camera_model="fisheye"), dict(render_mode="RGB+N"), dict(rasterize_mode="mip"),
     dict(sh_degree=5)],
    ids=lambda k: next(iter(k)),
)
def test_unsupported_arguments_raise_one_line(kw):
    s = one_gaussian()
    with pytest.raises(UnsupportedArgumentError) as err:
        rasterization(**s, **kw)
    assert "\n" not in str(err.value) and next(iter(kw)) in str(err.value)


def test_bad_shapes_raise():
    s = one_gaussian()
    with pytest.raises(ValueError, match="opacities"):
        rasterization(**{**s, "opacities": s["opacities"][:, None]})


def test_covars_and_ortho_supported():
    scene = make_scene(n=20, seed=6)
    from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci

    covars, _ = _quat_scale_to_covar_preci(scene["quats"], scene["scales"], True, False)
    r1, a1, _ = rasterization(**scene)
    r2, a2, _ = rasterization(**{**scene, "quats": None, "scales": None}, covars=covars)
    torch.testing.assert_close(r1, r2)
    r3, a3, meta = rasterization(**{**scene, "Ks": scene["Ks"] * torch.tensor([[[8, 1, 1], [1, 8, 1], [1, 1, 1]]])},
                                 camera_model="ortho", packed=False)
    assert float(a3.max()) > 0.1 and torch.isfinite(r3).all()


# ----------------------------------------------------------------------------------------------------------------
# Stability: degenerate inputs give finite images and finite gradients; invalid Gaussians are dropped
# ----------------------------------------------------------------------------------------------------------------


def _with_degenerates(dtype):
    scene = make_scene(n=24, seed=7, dtype=dtype)
    means, quats, scales, opac, cols = (scene[k].clone() for k in PARAMS)
    big = torch.finfo(dtype).max
    # rows 0..: the degenerate cases
    scales[0] = 0.0  # zero scale
    scales[1] = 1e6  # huge scale (covers everything)
    scales[2] = big / 10  # overflows
    quats[3] = 0.0  # zero quaternion
    quats[4] = quats[4] * 1e-12  # tiny, unnormalised
    quats[5] = quats[5] * 1e12  # huge, unnormalised
    cam_to_world = torch.inverse(scene["viewmats"][0])

    def at(x, y, z):  # a point given in camera coordinates
        return (cam_to_world @ torch.tensor([x, y, z, 1.0], dtype=dtype))[:3]

    means[6] = at(0.3, -0.2, 0.0)  # on the camera plane
    means[7] = at(0.1, 0.1, -2.0)  # behind the camera
    means[8] = at(0.001, 0.002, 0.02)  # just past the near plane (drawn, huge on screen)
    opac[9] = 0.0
    opac[10] = 1.0
    means[11] = big  # float extreme
    means[12, 0] = float("nan")  # NaN
    cols[13, 1] = float("inf")
    scales[14, 2] = float("nan")
    quats[15, 0] = float("inf")
    means[16] = at(0.0, 0.0, 1e20)  # beyond the far plane
    means[17] = at(0.0, 0.0, 0.005)  # in front of the camera but closer than the near plane
    scene.update(means=means, quats=quats, scales=scales, opacities=opac, colors=cols)
    return scene


INVALID_ROWS = [2, 3, 6, 7, 11, 12, 13, 14, 15, 16, 17]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_degenerate_inputs_give_finite_images_and_gradients(dtype, mode):
    scene = _with_degenerates(dtype)
    r, a, meta, g = render_and_grad(rasterization, scene, packed=False, absgrad=True, rasterize_mode=mode,
                                    render_mode="RGB+ED")
    assert torch.isfinite(r).all() and torch.isfinite(a).all()
    assert ((a >= 0) & (a <= 1)).all()
    for k in PARAMS:
        assert torch.isfinite(g[k]).all(), k
        assert float(g[k][INVALID_ROWS].abs().sum()) == 0.0, k  # dropped: zero gradient
    assert torch.isfinite(meta["means2d"].grad).all() and torch.isfinite(meta["means2d"].absgrad).all()
    assert (meta["radii"][0, INVALID_ROWS] == 0).all()
    # Dropping the invalid rows beforehand gives the same image: they never poison it.
    keep = [i for i in range(24) if i not in INVALID_ROWS]
    clean = {k: (v[keep] if k in PARAMS else v) for k, v in scene.items()}
    r2, a2, _ = rasterization(**clean, packed=False, rasterize_mode=mode, render_mode="RGB+ED")
    torch.testing.assert_close(r, r2, rtol=0, atol=0)
    torch.testing.assert_close(a, a2, rtol=0, atol=0)
    # and the healthy degenerate-but-valid ones are drawn (zero scale, huge scale, unnormalised quaternions,
    # near the near plane, opacity 1)
    assert (meta["radii"][0, [0, 1, 4, 5, 8, 10]] > 0).all()


def test_many_overlapping_gaussians_at_one_pixel():
    n = 3000
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * 0.01 + torch.tensor([0.0, 0.0, 2.0])
    scene = dict(means=means, quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), 0.05),
                 opacities=torch.full((n,), 0.999), colors=torch.rand(n, 3, generator=g),
                 viewmats=torch.eye(4)[None], Ks=torch.tensor([[[32.0, 0, 16], [0, 32, 16], [0, 0, 1]]]),
                 width=32, height=32)
    r, a, meta, grads = render_and_grad(rasterization, scene, absgrad=True, packed=False)
    assert torch.isfinite(r).all() and all(torch.isfinite(v).all() for v in grads.values())
    assert float(a[0, 16, 16, 0]) > 1 - 1e-3  # saturated
    assert float(a.max()) <= 1 - 1e-4 + 1e-6  # never past the stop threshold
    # the pixel stops after a couple of Gaussians: most of the 3000 get no gradient
    assert int((grads["opacities"] != 0).sum()) < n


# ----------------------------------------------------------------------------------------------------------------
# Randomised (hypothesis)
# ----------------------------------------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 24),
    width=st.integers(4, 40),
    height=st.integers(4, 40),
    n_cameras=st.integers(1, 2),
    packed=st.booleans(),
    mode=st.sampled_from(["classic", "antialiased"]),
    render_mode=st.sampled_from(["RGB", "D", "ED", "RGB+D", "RGB+ED"]),
    sh_degree=st.sampled_from([None, 0, 1, 2, 3]),
    log_scale=st.floats(-4.0, 0.5),
    opacity_edge=st.sampled_from([None, 0.0, 1.0]),
    tile_size=st.sampled_from([16, 16, 8]),
)
def test_randomised_against_reference(seed, n, width, height, n_cameras, packed, mode, render_mode, sh_degree,
                                      log_scale, opacity_edge, tile_size):
    scene = make_scene(n=n, seed=seed, width=width, height=height, n_cameras=n_cameras, sh_degree=sh_degree,
                       scale_range=(0.3 * 10**log_scale, 10**log_scale))
    if opacity_edge is not None:
        scene["opacities"][0] = opacity_edge
    kw = dict(rasterize_mode=mode, render_mode=render_mode, tile_size=tile_size)
    r_ref, a_ref, m_ref, g_ref = render_and_grad(reference_rasterization, scene, packed=packed, **kw)
    r, a, meta, g = render_and_grad(rasterization, scene, packed=packed, absgrad=True, **kw)
    torch.testing.assert_close(r, r_ref, rtol=1e-8, atol=1e-9)
    torch.testing.assert_close(a, a_ref, rtol=1e-8, atol=1e-9)
    for k in PARAMS:
        if g[k] is None:  # colours in "D"/"ED"
            assert g_ref[k] is None and render_mode in ("D", "ED")
            continue
        ref = g_ref[k] if g_ref[k] is not None else torch.zeros_like(g[k])  # nothing visible: zero gradient
        assert torch.isfinite(g[k]).all()
        assert float((g[k] - ref).norm()) <= 1e-8 * (1 + float(ref.norm())), k


def test_small_matmul_broadcast_path_equals_matmul():
    # The CUDA path of the projection (broadcast outer products) must be the same maths as `@` (the CPU path).
    from hpgs_ns.cpu_raster import _mm_broadcast

    g = torch.Generator().manual_seed(0)
    shapes = [((5, 3, 3), (5, 3, 3)), ((2, 1, 3, 3), (4, 3, 3)), ((7, 2, 3), (7, 3, 3)), ((6, 3, 3), (6, 3, 1)), ((6, 1, 16), (6, 16, 3))]
    for sa, sb in shapes:
        a = torch.randn(*sa, generator=g, dtype=torch.float64)
        b = torch.randn(*sb, generator=g, dtype=torch.float64)
        torch.testing.assert_close(_mm_broadcast(a, b), a @ b, rtol=0, atol=1e-12)
