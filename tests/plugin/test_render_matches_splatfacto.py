"""The model renders as stock splatfacto does: `HpgsSplatfactoModel` (its one render method, behind training, eval
and selection renders and the pair renders' constants) against nerfstudio 1.1.5's `SplatfactoModel.get_outputs`,
same Gaussians and cameras, on the CPU.

Stock splatfacto runs here with only its CUDA-bound pieces swapped, never its maths: gsplat's `rasterization` (the
name splatfacto imported) is `hpgs_ns.cpu_raster.rasterization`, `Tensor.cuda` is the identity, its
`torch.compile`d `get_viewmat` runs uncompiled, and its LPIPS (an AlexNet download) is a stand-in no test reads.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox, SceneBox
from nerfstudio.models.splatfacto import SplatfactoModelConfig

from hpgs_ns.model import HpgsSplatfactoModelConfig
from hpgs_ns.render.pair_render import render_pairs
from hpgs_ns.render.viewmats import world_to_camera

TOL = 1e-6
N_CAMERAS, WIDTH, HEIGHT = 3, 40, 30
STEP = 2  # SH degree 2 of 3 (interval 1), half resolution while training (num_downscales 1)
CASES = [
    pytest.param({"sh_degree": 3, "rasterize_mode": "classic", "background_color": "random"}, id="sh3-classic-random"),
    pytest.param({"sh_degree": 0, "rasterize_mode": "antialiased", "background_color": "white"}, id="rgb-aa-white"),
    pytest.param({"sh_degree": 1, "rasterize_mode": "classic", "background_color": "black", "use_bilateral_grid": True},
                 id="sh1-black-bilagrid"),
]


@pytest.fixture(autouse=True)
def _stock_splatfacto_on_cpu(monkeypatch):
    import gsplat.rendering
    import torchmetrics.image.lpip
    from nerfstudio.models import splatfacto

    from hpgs_ns import cpu_raster

    torch.set_num_threads(1)
    monkeypatch.setattr(gsplat.rendering, "rasterization", cpu_raster.rasterization)
    monkeypatch.setattr(splatfacto, "rasterization", cpu_raster.rasterization)
    monkeypatch.setattr(torch.Tensor, "cuda", lambda self, *args, **kwargs: self)
    # Its own function, uncompiled: an inductor C++ build per shape would cost minutes and test nothing of splatfacto.
    monkeypatch.setattr(splatfacto, "get_viewmat", splatfacto.get_viewmat.__wrapped__)
    monkeypatch.setattr(torchmetrics.image.lpip, "LearnedPerceptualImagePatchSimilarity", lambda **_: torch.nn.Module())


def ring_cameras() -> Cameras:
    """N_CAMERAS views of the origin from a circle of radius 3 (nerfstudio's OpenGL camera-to-world poses)."""
    poses = []
    for k in range(N_CAMERAS):
        a = 2 * math.pi * k / N_CAMERAS
        eye = torch.tensor([3 * math.cos(a), 3 * math.sin(a), 0.5])
        back = eye / eye.norm()
        right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back)
        right = right / right.norm()
        up = torch.linalg.cross(back, right)
        poses.append(torch.cat([torch.stack([right, up, back], 1), eye[:, None]], 1))
    return Cameras(camera_to_worlds=torch.stack(poses), fx=30.0, fy=32.0, cx=WIDTH / 2 + 1, cy=HEIGHT / 2 - 1,
                   width=WIDTH, height=HEIGHT, metadata={"cam_idx": 0})


def models(case: dict):
    """(ours, stock): the same 400 Gaussians (randomised around splatfacto's seeded init), pose corrections and
    bilateral grids, at step STEP."""
    g = torch.Generator().manual_seed(0)
    seed_points = (torch.randn(400, 3, generator=g) * 0.6, torch.randint(0, 256, (400, 3), generator=g).byte())
    common = dict(case, sh_degree_interval=1, num_downscales=1, camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"))
    setup = {"scene_box": SceneBox(torch.tensor([[-1.0] * 3, [1.0] * 3])), "num_train_data": N_CAMERAS,
             "seed_points": seed_points}
    ours = HpgsSplatfactoModelConfig(rasterizer="cpu", **common).setup(**setup)
    stock = SplatfactoModelConfig(**common).setup(**setup)
    with torch.no_grad():
        for name, param in ours.gauss_params.items():
            param.add_(torch.randn(param.shape, generator=g) * 0.2)
            stock.gauss_params[name] = torch.nn.Parameter(param.detach().clone())
        for param in ours.get_param_groups()["camera_opt"]:
            param.copy_(torch.randn(param.shape, generator=g) * 0.02)
        for mine, theirs in zip(ours.get_param_groups().values(), stock.get_param_groups().values(), strict=True):
            for p, q in zip(mine, theirs, strict=True):
                q.copy_(p)
    return ours, stock


class _Optimizers:
    optimizers: dict = {}


def outputs(model, camera: Cameras, training: bool) -> dict:
    model.train(training)
    if training:
        model.step_cb(_Optimizers(), STEP)
    else:
        model.step = STEP
    torch.manual_seed(1)  # the random training background
    return model.get_outputs(copy.deepcopy(camera))


def assert_close(a: torch.Tensor, b: torch.Tensor, what: str) -> None:
    assert a.shape == b.shape, (what, a.shape, b.shape)
    assert (a - b).abs().max() < TOL, (what, float((a - b).abs().max()))


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("crop", [False, True])
def test_eval_render_and_selection_renders_match_stock(case, crop):
    ours, stock = models(case)
    if crop:  # the viewer's crop box: only the Gaussians inside are rendered
        box = OrientedBox(R=torch.eye(3), T=torch.tensor([0.2, 0.0, 0.0]), S=torch.tensor([1.2, 1.0, 1.4]))
        ours.set_crop(box)
        stock.set_crop(box)
    cameras = ring_cameras()
    references = []
    for k in range(N_CAMERAS):
        mine, theirs = outputs(ours, cameras[k : k + 1], False), outputs(stock, cameras[k : k + 1], False)
        for key in ("rgb", "depth", "accumulation", "background"):
            assert_close(mine[key], theirs[key], key)
        references.append(theirs["rgb"])
    if crop:
        return  # selection renders the whole splat
    # Selection: all views in one batched call, and at a reduced size.
    for k, image in enumerate(ours.render_views(cameras)):
        assert_close(image, references[k], f"render_views {k}")
    small = copy.deepcopy(cameras)
    small.rescale_output_resolution(0.5)
    stock.eval()
    for k, image in enumerate(ours.render_views(cameras, short_side=HEIGHT // 2)):
        assert_close(image, stock.get_outputs(small[k : k + 1])["rgb"], f"render_views short side {k}")
    # FisherRF's pair renders of `splat()`: the same image before the clamp (packed layout; float32 round-off).
    viewmats = world_to_camera(cameras.camera_to_worlds)
    with ours.eval_mode():
        pairs = render_pairs(ours.splat(), viewmats, cameras.get_intrinsics_matrices(), WIDTH, HEIGHT, ())
    for k in range(N_CAMERAS):
        assert (pairs.image[k].clamp(0, 1) - references[k]).abs().max() < 1e-5


@pytest.mark.parametrize("case", CASES)
def test_training_render_gradients_and_strategy_state_match_stock(case):
    """Training: pose-refined camera, downscaled, random background; the same image, the same gradients of every
    parameter, and the same densification statistics after the strategy's hooks."""
    ours, stock = models(case)
    camera = ring_cameras()[1:2]
    mine, theirs = outputs(ours, camera, True), outputs(stock, camera, True)
    assert mine["rgb"].shape == (HEIGHT // 2, WIDTH // 2, 3)
    assert_close(mine["rgb"], theirs["rgb"], "rgb")
    assert_close(mine["accumulation"], theirs["accumulation"], "accumulation")
    weights = torch.randn(mine["rgb"].shape, generator=torch.Generator().manual_seed(2))
    (mine["rgb"] * weights).sum().backward()
    (theirs["rgb"] * weights).sum().backward()
    for (name, groups), theirs_groups in zip(ours.get_param_groups().items(), stock.get_param_groups().values(),
                                             strict=True):
        for p, q in zip(groups, theirs_groups, strict=True):
            assert p.grad is not None, name
            assert torch.allclose(p.grad, q.grad, rtol=TOL, atol=TOL), (name, float((p.grad - q.grad).abs().max()))
    assert_close(ours.info["means2d"].grad, stock.info["means2d"].grad, "means2d grad")
    assert_close(ours.info["means2d"].absgrad, stock.info["means2d"].absgrad, "means2d absgrad")
    ours.step_post_backward(STEP)
    stock.step_post_backward(STEP)
    for key in ("grad2d", "count", "radii"):
        assert ours.strategy_state[key] is not None, key
        assert_close(ours.strategy_state[key], stock.strategy_state[key], key)
