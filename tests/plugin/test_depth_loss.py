"""The depth loss (`hpgs_ns.strategies.depth_loss`): HP-GS's disparity-space depth term, at the sparse points the
active views see. Its residual by hand, zero where the render's depth is the points', no point of a withheld or test
view, the CPU twin's expected-depth gradient against the reference built on gsplat's torch twin, the option's one
line, and a few real `hpgs` steps on a 64 px copy of a real capture."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import require_shared, short_config
from test_cpu_raster import PARAMS, make_scene, reference_rasterization
from test_judge_scenes import small_copy

from hpgs_ns.cpu_raster import rasterization
from hpgs_ns.errors import OptionError
from hpgs_ns.strategies import registry
from hpgs_ns.strategies.base import ActiveViews, RenderedView, TrackedPoints
from hpgs_ns.strategies.depth_loss import DepthLoss, DepthLossConfig, disparity_residuals, project

F64 = torch.float64


def pinhole(width=8, height=6, f=10.0):
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=F64)
    return torch.eye(4, dtype=F64), K  # camera at the origin looking down +z (OpenCV)


def test_the_residual_is_the_hand_computed_disparity_difference():
    viewmat, K = pinhole()
    depth = torch.full((6, 8, 1), 2.0, dtype=F64)
    depth[1, 6] = 4.0
    # pixel (col, row) of a point at z: (10 x / z + 4, 10 y / z + 3)
    points = torch.tensor([
        [0.0, 0.0, 1.0],      # pixel (4, 3): |1/2 - 1/1| = 0.5
        [0.25, -0.2, 1.0],    # pixel (6.5, 1.0) -> (6, 1): |1/4 - 1/1| = 0.75
        [0.1, 0.1, 5.0],      # pixel (4.2, 3.2) -> (4, 3): |1/2 - 1/5| = 0.3
        [0.0, 0.0, -1.0],     # behind the camera: left out
        [5.0, 0.0, 1.0],      # outside the image: left out
        [0.0, 0.0, 0.0],      # zero depth: left out
    ], dtype=F64)
    residuals = disparity_residuals(points, viewmat, K, depth)
    assert torch.allclose(residuals, torch.tensor([0.5, 0.75, 0.3], dtype=F64))
    # and as the strategy's term, for a view that observes them all: weight x the mean
    loss = DepthLoss(DepthLossConfig(weight=0.1))
    loss.after_views_added(None, ActiveViews([0], TrackedPoints(points.float(), torch.ones(6, 1, dtype=torch.bool))))
    model = type("M", (), {"last_view": RenderedView(0, viewmat, K, 8, 6)})()
    term = loss.loss(model, {"depth": depth.float(), "accumulation": torch.ones(6, 8, 1)}, {}, step=0)["depth_loss"]
    assert term.item() == pytest.approx(0.1 * (0.5 + 0.75 + 0.3) / 3, rel=1e-6)
    assert loss.loss(model, {"depth": depth.float()}, {}, step=0)["depth_loss"].isfinite()
    # before start-step: no term
    late = DepthLoss(DepthLossConfig(weight=0.1, start_step=10))
    late.xyz, late.observers = loss.xyz, loss.observers
    assert late.loss(model, {"depth": depth.float()}, {}, step=9) == {}


def test_it_is_zero_where_the_render_s_depth_is_the_points_depth():
    scene = make_scene(n=25, seed=3, width=32, height=24)
    render, alpha, _ = rasterization(**{k: scene[k] for k in PARAMS}, viewmats=scene["viewmats"], Ks=scene["Ks"],
                                     width=32, height=24, render_mode="RGB+ED")
    depth, alpha = render[0, ..., 3], alpha[0, ..., 0]
    rows, cols = torch.nonzero(alpha > 0.5, as_tuple=True)
    assert rows.numel() > 20
    d = depth[rows, cols]
    # back-project each covered pixel's centre at the rendered depth
    K, viewmat = scene["Ks"][0], scene["viewmats"][0]
    x = (cols.to(F64) + 0.5 - K[0, 2]) / K[0, 0] * d
    y = (rows.to(F64) + 0.5 - K[1, 2]) / K[1, 1] * d
    cam = torch.stack([x, y, d], -1)
    world = (cam - viewmat[:3, 3]) @ viewmat[:3, :3]  # R^T (cam - t)
    uv, z = project(world, viewmat, K)
    assert torch.allclose(z, d)
    residuals = disparity_residuals(world, viewmat, K, depth, alpha)
    assert residuals.numel() == rows.numel()
    assert residuals.max().item() < 1e-9
    # moved 10% farther, the residual is 1/d - 1/(1.1 d)
    farther = disparity_residuals((cam * 1.1 - viewmat[:3, 3]) @ viewmat[:3, :3], viewmat, K, depth, alpha)
    assert torch.allclose(farther, 1 / d - 1 / (1.1 * d))


def test_a_point_only_a_withheld_or_test_view_sees_is_never_used():
    viewmat, K = pinhole()
    xyz = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.0, 0.1, 1.0]])
    # views 0 and 2 active, 1 withheld; point 0 seen by 0 and 1, point 1 only by 1, point 2 by nobody in the split
    # (a test view's point: the training split has no column for it)
    observers = torch.tensor([[1, 1, 0], [0, 1, 0], [0, 0, 0]], dtype=torch.bool)
    loss = DepthLoss(DepthLossConfig(weight=1.0))
    loss.after_views_added(None, ActiveViews([0, 2], TrackedPoints(xyz, observers)))
    assert loss.xyz.tolist() == [[0.0, 0.0, 1.0]]
    assert loss.observers.tolist() == [[True, False, False]]  # the withheld view's observation is dropped
    depth = torch.full((6, 8, 1), 2.0)
    for view, expected in ((0, 0.5), (2, 0.0)):
        model = type("M", (), {"last_view": RenderedView(view, viewmat, K, 8, 6)})()
        assert loss.loss(model, {"depth": depth}, {}, step=0)["depth_loss"].item() == pytest.approx(expected)
    # once view 1 is added, point 1 joins
    loss.after_views_added(None, ActiveViews([0, 1, 2], TrackedPoints(xyz, observers)))
    assert loss.xyz.shape[0] == 2


def test_the_cpu_twin_s_expected_depth_gradient_matches_gsplat_s_torch_twin():
    """The disparity loss through the CPU twin's RGB+ED render: its gradients equal those through the reference
    (projection by gsplat's `_torch_impl`, a per-pixel loop from gsplat's kernel), and finite differences."""
    scene = make_scene(n=12, seed=5, width=20, height=16)
    viewmat, K = scene["viewmats"][0], scene["Ks"][0]
    g = torch.Generator().manual_seed(1)
    points = torch.randn(40, 3, generator=g, dtype=F64) * 0.5

    def loss_of(fn, params):
        render, alpha = fn(**params, viewmats=scene["viewmats"], Ks=scene["Ks"], width=20, height=16,
                           render_mode="RGB+ED")[:2]
        return disparity_residuals(points, viewmat, K, render[0, ..., 3], alpha[0]).mean()

    grads = {}
    for name, fn in (("twin", rasterization), ("reference", reference_rasterization)):
        params = {k: scene[k].clone().requires_grad_() for k in PARAMS}
        value = loss_of(fn, params)
        value.backward()
        grads[name] = (value.detach(), {k: params[k].grad for k in ("means", "scales", "opacities", "quats")})
    assert torch.isfinite(grads["twin"][0]) and grads["twin"][0] > 0
    assert torch.allclose(grads["twin"][0], grads["reference"][0], atol=1e-12)
    for k, grad in grads["twin"][1].items():
        assert grad.abs().sum() > 0, k
        assert torch.allclose(grad, grads["reference"][1][k], atol=1e-9, rtol=1e-7), k
    # finite differences of the twin, on a few means' coordinates
    params = {k: scene[k].clone() for k in PARAMS}
    flat = grads["twin"][1]["means"].flatten()
    for i in torch.topk(flat.abs(), 3).indices.tolist():
        h = 1e-6
        plus, minus = {**params, "means": params["means"].clone()}, {**params, "means": params["means"].clone()}
        plus["means"].view(-1)[i] += h
        minus["means"].view(-1)[i] -= h
        numeric = (loss_of(rasterization, plus) - loss_of(rasterization, minus)) / (2 * h)
        assert numeric.item() == pytest.approx(flat[i].item(), rel=1e-4, abs=1e-9)


@pytest.mark.parametrize("weight", [-0.1, math.nan, math.inf])
def test_a_bad_weight_is_one_line(weight):
    with pytest.raises(OptionError) as err:
        DepthLossConfig(weight=weight)
    message = str(err.value)
    assert message.startswith(f"--pipeline.model.depth-loss.weight {weight}: must be a finite weight >= 0; ")
    assert "\n" not in message


def test_the_registry_gives_the_model_its_option_group():
    from dataclasses import fields

    from hpgs_ns.model import HpgsSplatfactoModelConfig

    assert registry.BUILTIN_STRATEGIES["depth-loss"] == "hpgs_ns.strategies.depth_loss:DepthLossConfig"
    config = HpgsSplatfactoModelConfig()
    assert "depth_loss" in {f.name for f in fields(config)}
    assert config.depth_loss.weight == 0.0 and not config.depth_loss.active()  # off by default: nothing built
    assert list(config.strategy_configs()) == registry.strategy_names()  # every registered one, in its order


def test_a_start_without_points_says_the_loss_does_nothing(capsys):
    loss = DepthLoss(DepthLossConfig(weight=0.2))
    loss.after_views_added(None, ActiveViews([0, 1], None, "seed-points random drops the capture's points"))
    said = capsys.readouterr().out
    assert "--pipeline.model.depth-loss.weight 0.2 does nothing in this run: seed-points random" in said
    assert loss.loss(type("M", (), {"last_view": None})(), {"depth": torch.ones(2, 2, 1)}, {}, 0) == {}


def test_a_few_hpgs_steps_on_a_real_capture_train_with_the_depth_loss(tmp_path, capsys):
    source = require_shared("data", "gerrard-hall")
    factor = small_copy(source, tmp_path / "scene")
    cfg = short_config(tmp_path / "scene", tmp_path / "out", steps=6, every=3, rounds=1, initial=4)
    cfg.pipeline.datamanager.dataparser.downscale_factor = factor
    cfg.pipeline.model.depth_loss.weight = 0.1
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline, dm, model = trainer.pipeline, trainer.pipeline.datamanager, trainer.pipeline.model
    assert dm.seed_points_mode == "colmap"
    assert "depth loss 0.1: disparity at the" in capsys.readouterr().out
    # every point the loss holds is seen by an active view, and by no other view in its kept track
    strategy = model.strategies_by_name["depth-loss"]
    inactive = torch.ones(strategy.observers.shape[1], dtype=torch.bool)
    inactive[torch.tensor(dm.active)] = False
    assert strategy.xyz.shape[0] > 100 and strategy.observers.any(1).all()
    assert not strategy.observers[:, inactive].any()
    assert pipeline.datamanager.selection_signature["depth-loss"] == "0.1 from 0"
    terms = []
    original = model.get_loss_dict

    def recording(outputs, batch, metrics_dict=None):
        out = original(outputs, batch, metrics_dict)
        terms.append(out["depth_loss"].item())
        return out

    model.get_loss_dict = recording
    points_before = strategy.xyz.shape[0]
    trainer.train()
    assert len(terms) == 6 and all(math.isfinite(t) for t in terms) and max(terms) > 0
    assert len(dm.active) == 5 and strategy.xyz.shape[0] >= points_before  # rebuilt after the round's add
