"""Per-pair rendering (what `fisher` batches views with): same image as the rasterizer, and each view's own gradient
from one backward pass over a batch of views."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from hpgs_ns.cpu_raster import rasterization
from hpgs_ns.render.pair_render import Splat, render_pairs, sh_squared_gradients
from hpgs_ns.render.rasterize import rasterize_splat
from hpgs_ns.selectors.fisher import FisherSelectorConfig

torch.set_num_threads(1)


def random_splat(n: int = 300, sh_degree: int = 1, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    params = {
        "means": torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.6,
        "scales": torch.log(torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.08 + 0.02),
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "opacities": torch.randn(n, 1, generator=g, dtype=torch.float64),
        "features_dc": torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5,
        "features_rest": torch.randn(n, k - 1, 3, generator=g, dtype=torch.float64) * 0.1,
    }
    config = SimpleNamespace(sh_degree=sh_degree, sh_degree_interval=1, rasterize_mode="classic")
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    return SimpleNamespace(gauss_params=params, config=config, step=10, background_color=background)


def as_splat(model, backend: str = "cpu") -> Splat:
    """What `HpgsSplatfactoModel.splat()` returns, for the stand-in model above."""
    c = model.config
    degree = min(model.step // c.sh_degree_interval, c.sh_degree) if c.sh_degree > 0 else None
    return Splat(params=model.gauss_params, sh_degree=degree, background=model.background_color,
                 antialiased=c.rasterize_mode == "antialiased", backend=backend)


def ring_cameras(c: int = 3, width: int = 24, height: int = 18):
    """Cameras on a circle of radius 3 looking at the origin (OpenCV convention, world-to-camera)."""
    viewmats = []
    for k in range(c):
        a = 2 * math.pi * k / c
        eye = torch.tensor([3 * math.cos(a), 3 * math.sin(a), 0.4], dtype=torch.float64)
        fwd = -eye / eye.norm()
        right = torch.linalg.cross(fwd, torch.tensor([0, 0, 1.0], dtype=torch.float64))
        right = right / right.norm()
        down = torch.linalg.cross(fwd, right)
        R = torch.stack([right, down, fwd])
        vm = torch.eye(4, dtype=torch.float64)
        vm[:3, :3], vm[:3, 3] = R, -R @ eye
        viewmats.append(vm)
    K = torch.tensor([[20.0, 0, width / 2], [0, 20.0, height / 2], [0, 0, 1]], dtype=torch.float64)
    return torch.stack(viewmats), K.expand(c, 3, 3).contiguous(), width, height


def plain_render(model, viewmats, Ks, W, H, leaves=None):
    """The model's own rasterization call (`HpgsSplatfactoModel._rasterize_cameras`'s), composited but not clamped
    (as pair renders are)."""
    splat = as_splat(model)
    img, alpha, _ = rasterize_splat(rasterization, leaves or splat.params, splat.sh_degree, viewmats, Ks, W, H)
    return img + (1 - alpha) * model.background_color


@pytest.mark.parametrize("sh_degree", [0, 1])
def test_pair_render_matches_the_rasterizer(sh_degree):
    model = random_splat(sh_degree=sh_degree)
    if sh_degree == 0:
        model.config.sh_degree = 0
        model.gauss_params["features_rest"] = model.gauss_params["features_rest"][:, :0]
    viewmats, Ks, W, H = ring_cameras()
    pr = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, ())
    ref = plain_render(model, viewmats, Ks, W, H)
    assert pr.image.shape == (3, H, W, 3)
    assert (pr.image - ref).abs().max() < 1e-9
    # Frustum culling: each view holds only the Gaussians that reach it, never all of them for every view.
    assert pr.camera_ids.numel() < 3 * 300 and pr.camera_ids.numel() > 0


def test_one_backward_gives_each_views_own_gradient():
    """With a probe eps on all views, the pairs of view c sum (per Gaussian) to the gradient of view c alone."""
    model = random_splat()
    viewmats, Ks, W, H = ring_cameras()
    names = ("means", "features_dc", "features_rest", "scales", "opacities")
    pr = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, names)
    eps = torch.randint(0, 2, pr.image.shape, generator=torch.Generator().manual_seed(1)).double() * 2 - 1
    grads = torch.autograd.grad(pr.image, [pr.leaves[n] for n in names], grad_outputs=eps)
    for c in range(3):
        leaves = {n: t.clone().requires_grad_(n in names) for n, t in model.gauss_params.items()}
        img = plain_render(model, viewmats[c : c + 1], Ks[c : c + 1], W, H, leaves)
        ref = torch.autograd.grad(img, [leaves[n] for n in names], grad_outputs=eps[c : c + 1])
        mine = pr.camera_ids == c
        for name, g, r in zip(names, grads, ref, strict=True):
            per_gauss = torch.zeros_like(r).index_add_(0, pr.gaussian_ids[mine], g[mine])
            assert torch.allclose(per_gauss, r, rtol=1e-7, atol=1e-10), (c, name, (per_gauss - r).abs().max())


@pytest.mark.parametrize("interval, degree", [(10, 1), (1, 3)])
def test_sh_squared_gradients_from_the_colour_gradient_equal_autograds(interval, degree):
    """`sh_via_color`: B_k^2 * d^2 is each SH coefficient's squared gradient (zero above the active degree)."""
    model = random_splat(sh_degree=3)
    model.config.sh_degree_interval = interval  # step 10: active degree 10 // interval, at most 3
    viewmats, Ks, W, H = ring_cameras()
    names = ("means", "features_dc", "features_rest", "scales", "opacities")
    full = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, names)
    fast = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, names, sh_via_color=True)
    assert torch.equal(full.image, fast.image) and fast.sh_bases.shape[1] == (degree + 1) ** 2
    assert not fast.leaves["features_rest"].requires_grad
    eps = torch.randint(0, 2, full.image.shape, generator=torch.Generator().manual_seed(3)).double() * 2 - 1
    g_full = torch.autograd.grad(full.image, [full.leaves[n] for n in names], grad_outputs=eps, retain_graph=True)
    g_full = dict(zip(names, g_full, strict=True))
    direct = ("means", "scales", "opacities")
    fast_inputs = [fast.leaves[n] for n in direct] + [fast.color_offset]
    g_fast = torch.autograd.grad(fast.image, fast_inputs, grad_outputs=eps, retain_graph=True)
    dc, rest = sh_squared_gradients(fast.sh_bases, g_fast[-1].square(), 15)
    assert torch.allclose(dc, g_full["features_dc"].square(), rtol=1e-10, atol=1e-15)
    assert torch.allclose(rest, g_full["features_rest"].square(), rtol=1e-10, atol=1e-15)
    assert rest[:, (degree + 1) ** 2 - 1 :].abs().sum() == 0 and rest[:, : (degree + 1) ** 2 - 1].abs().max() > 0
    # The means still get their path through the viewing direction.
    for name, g in zip(direct, g_fast[:-1], strict=True):
        assert torch.allclose(g, g_full[name], rtol=1e-10, atol=1e-15), name

    # The Fisher selector's per-pair diagonal is the same either way (same probes).
    selector = FisherSelectorConfig(probes=4).setup()
    both = [selector.pair_squares(pr, 4, torch.Generator().manual_seed(4)) for pr in (full, fast)]
    assert both[0].keys() == both[1].keys() == set(names)
    for name in names:
        assert torch.allclose(both[0][name], both[1][name], rtol=1e-10, atol=1e-15), name


@pytest.mark.parametrize("sh_degree, rotations, mode", [(3, False, "classic"), (0, True, "antialiased")])
def test_linearized_gradients_equal_autograds(sh_degree, rotations, mode):
    """`linearize`: the rasterizer's backward chained with each pair's projection Jacobian gives every pair the
    gradient autograd gives it through the whole graph (SH through the colour; sigmoid RGB chained like the rest;
    the antialiased compensation and the quaternions included)."""
    model = random_splat(sh_degree=max(sh_degree, 1))
    model.config.rasterize_mode = mode
    if sh_degree == 0:
        model.config.sh_degree = 0
        model.gauss_params["features_rest"] = model.gauss_params["features_rest"][:, :0]
    model.gauss_params["features_dc"] = model.gauss_params["features_dc"] - 0.4  # some colours clamped at 0
    viewmats, Ks, W, H = ring_cameras()
    names = ["means", "features_dc", "features_rest", "scales", "opacities"] + (["quats"] if rotations else [])
    full = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, names)
    lin = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, names, linearize=True)
    assert torch.allclose(lin.image, full.image, rtol=0, atol=1e-12)
    assert torch.equal(lin.camera_ids, full.camera_ids) and not lin.leaves["means"].requires_grad
    assert lin.jacobian.shape == (full.camera_ids.numel(), 9, 7 + 4 * rotations + 3 * (sh_degree == 0))
    eps = torch.randint(0, 2, full.image.shape, generator=torch.Generator().manual_seed(6)).double() * 2 - 1
    g_full = full.gradients(eps)
    g_lin = lin.gradients(eps)
    for name in [n for n in names if sh_degree == 0 or n not in ("features_dc", "features_rest")]:
        mine, ref = g_lin[name], g_full[name]
        assert torch.allclose(mine, ref, rtol=1e-9, atol=1e-13), (name, (mine - ref).abs().max())
    if sh_degree:
        assert 0 < int((lin.color_mask == 0).sum()) < lin.color_mask.numel()  # the clamp is exercised
        dc, rest = sh_squared_gradients(lin.sh_bases, g_lin["color"].square(), 15)
        assert torch.allclose(dc, g_full["features_dc"].square(), rtol=1e-9, atol=1e-15)
        assert torch.allclose(rest, g_full["features_rest"].square(), rtol=1e-9, atol=1e-15)
    # The Fisher selector's per-pair diagonal is the same either way (same probes).
    selector = FisherSelectorConfig(probes=3, include_rotations=rotations).setup()
    both = [selector.pair_squares(pr, 3, torch.Generator().manual_seed(7)) for pr in (full, lin)]
    for name in selector.param_names():
        assert torch.allclose(both[0][name], both[1][name], rtol=1e-9, atol=1e-15), name


def test_drop_hidden_leaves_out_only_pairs_with_no_pixel():
    """Opaque Gaussians hide others: those pairs go, the image and every kept pair's gradient stay the same, and
    the dropped ones had exactly zero gradient."""
    model = random_splat(n=400)
    model.gauss_params["opacities"] = model.gauss_params["opacities"].abs() + 3.0  # sigmoid > 0.95: occlusion
    model.gauss_params["scales"] = model.gauss_params["scales"] + math.log(4.0)  # several pixels wide: overlap
    viewmats, Ks, W, H = ring_cameras()
    names = ("means", "features_dc", "features_rest", "scales", "opacities")
    full = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, names)
    kept = render_pairs(as_splat(model, "cpu"), viewmats, Ks, W, H, names, drop_hidden=True)
    assert kept.pairs_in_frustum == full.camera_ids.numel() > 1.2 * kept.camera_ids.numel() > 0  # ~30% hidden
    assert torch.allclose(kept.image, full.image, rtol=0, atol=1e-12)
    eps = torch.randint(0, 2, full.image.shape, generator=torch.Generator().manual_seed(5)).double() * 2 - 1
    g_full = torch.autograd.grad(full.image, [full.leaves[n] for n in names], grad_outputs=eps)
    g_kept = torch.autograd.grad(kept.image, [kept.leaves[n] for n in names], grad_outputs=eps)
    n_gauss = model.gauss_params["means"].shape[0]
    key = lambda pr: pr.camera_ids * n_gauss + pr.gaussian_ids  # noqa: E731
    where = {int(k): i for i, k in enumerate(key(full))}
    rows = torch.tensor([where[int(k)] for k in key(kept)])
    dropped = torch.ones(full.camera_ids.numel(), dtype=torch.bool)
    dropped[rows] = False
    for name, gf, gk in zip(names, g_full, g_kept, strict=True):
        assert torch.allclose(gk, gf[rows], rtol=1e-9, atol=1e-14), name
        assert gf[dropped].abs().max() == 0, name


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (gsplat's packed kernels)")
def test_gsplat_backend_matches_the_cpu_twin():
    model = random_splat(n=2000)
    for key, t in model.gauss_params.items():
        model.gauss_params[key] = t.float().cuda()
    model.background_color = model.background_color.float().cuda()
    viewmats, Ks, W, H = ring_cameras(4, 64, 48)
    viewmats, Ks = viewmats.float().cuda(), Ks.float().cuda()
    names = ("means", "features_dc", "scales", "opacities")
    out = {}
    for backend in ("gsplat", "cpu"):
        pr = render_pairs(as_splat(model, backend), viewmats, Ks, W, H, names)
        eps = torch.randint(0, 2, pr.image.shape, generator=torch.Generator().manual_seed(2)).cuda().float() * 2 - 1
        grads = torch.autograd.grad(pr.image, [pr.leaves[n] for n in names], grad_outputs=eps)
        out[backend] = (pr.image, grads)
    assert (out["gsplat"][0] - out["cpu"][0]).abs().max() < 1e-4
    for g, c in zip(out["gsplat"][1], out["cpu"][1], strict=True):
        assert (g - c).abs().max() <= 1e-3 * c.abs().max() + 1e-6


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (gsplat's packed kernels)")
def test_fisher_shortcuts_on_gsplat_keep_the_pair_diagonal():
    """`sh_via_color`, `drop_hidden` and `linearize` (the fisher defaults) on gsplat's kernels: same per-Gaussian
    diagonal."""
    model = random_splat(n=3000, sh_degree=3)
    model.gauss_params["scales"] = model.gauss_params["scales"] + math.log(4.0)
    model.gauss_params["opacities"] = model.gauss_params["opacities"].abs() + 2.0
    for key, t in model.gauss_params.items():
        model.gauss_params[key] = t.float().cuda()
    model.background_color = model.background_color.float().cuda()
    viewmats, Ks, W, H = ring_cameras(4, 32, 24)
    viewmats, Ks = viewmats.float().cuda(), Ks.float().cuda()
    names = ("means", "features_dc", "features_rest", "scales", "opacities")
    selector = FisherSelectorConfig(mode="exact").setup()  # every pixel-channel: no probe noise between the two
    diag = []
    for fast in (False, True):
        pr = render_pairs(as_splat(model, "gsplat"), viewmats, Ks, W, H, names, sh_via_color=fast, drop_hidden=fast,
                          linearize=fast)
        total = {n: torch.zeros_like(model.gauss_params[n]) for n in names}
        for n, sq in selector.pair_squares(pr, 1, torch.Generator(device="cuda")).items():
            total[n].index_add_(0, pr.gaussian_ids, sq)
        diag.append((pr, total))
    (full, d_full), (kept, d_kept) = diag
    assert kept.camera_ids.numel() < full.camera_ids.numel()
    assert (kept.image - full.image).abs().max() < 1e-5
    for n in names:
        assert (d_kept[n] - d_full[n]).abs().max() <= 1e-3 * d_full[n].abs().max() + 1e-8, n
