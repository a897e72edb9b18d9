"""`--pipeline.selection.after-add.restart-from splat`: a restart starts from the splat's own opaque Gaussians
(their centres and base colours, fresh sizes and opacities) instead of the run's step-0 points.

Tiny scene (CPU rasterizer), a random start (random-init, 1500 points) from 3 views, one round at step 20 of 40
adding 3 views: 3 -> 6 views, a restart (twice the initial count)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from conftest import run_training, short_config
from nerfstudio.models import splatfacto

from hpgs_ns.model import HpgsSplatfactoModel
from hpgs_ns.selection.after_add import AfterAddConfig

RESTART, TOTAL = 20, 40


@pytest.fixture(scope="module")
def run(tiny_scene, tmp_path_factory):
    cfg = short_config(tiny_scene, tmp_path_factory.mktemp("restart-splat"), steps=TOTAL, select_at=(RESTART,),
                       rounds=1, initial=3, views_per_round=3, selector="random")
    model = cfg.pipeline.model
    model.warmup_length, model.refine_every, model.reset_alpha_every, model.stop_split_at = 10, 10, 100, 60
    model.random_init, model.num_random = True, 1500
    cfg.pipeline.selection.after_add = AfterAddConfig(restart_from="splat")
    taken = []
    original = HpgsSplatfactoModel.opaque_points

    def spy(self):
        points = original(self)
        taken.append((points, int(self.num_points), torch.sigmoid(self.opacities.detach().squeeze(-1)).cpu()))
        return points

    HpgsSplatfactoModel.opaque_points = spy
    torch.manual_seed(0)
    try:
        trainer = run_training(cfg)
    finally:
        HpgsSplatfactoModel.opaque_points = original
    return {"trainer": trainer, "taken": taken}


def test_the_restart_starts_from_the_splats_opaque_gaussians(run):
    model = run["trainer"].pipeline.model
    assert len(run["taken"]) == 1
    (xyz, rgb), count_before, opacity_before = run["taken"][0]
    kept = int((opacity_before >= 0.1).sum())
    assert xyz.shape == (kept, 3) and 0 < kept < count_before  # random points the first views never made opaque go
    initial = model.initial_gaussians  # the state later resets return to: those points, as seed points start
    assert torch.equal(initial["means"], xyz)
    assert torch.allclose(torch.sigmoid(initial["opacities"]), torch.full((kept, 1), 0.1), atol=1e-6)
    colours = (splatfacto.SH2RGB(initial["features_dc"]).clamp(0, 1) * 255).round().to(torch.uint8)
    assert torch.equal(colours, rgb)
    assert float(initial["features_rest"].abs().sum()) == 0.0
    log = json.loads((Path(run["trainer"].base_dir) / "selected_views.json").read_text())
    (first,) = log["rounds"]
    assert first["reset"] and first["after_add"]["splat_points_restart"] == kept
    assert first["num_gaussians_before_reset"] == count_before and first["num_gaussians_after_reset"] == kept


@pytest.mark.parametrize("sh_degree", [3, 0])
def test_opaque_points_keeps_what_culling_keeps_in_its_colour(run, sh_degree):
    model = run["trainer"].pipeline.model
    saved = {k: v.detach().clone() for k, v in model.gauss_params.items()}
    saved_degree = model.config.sh_degree
    try:
        n = model.num_points
        opacity = torch.where(torch.arange(n) % 3 == 0, 0.05, 0.6)  # every third below the 0.1 culling threshold
        wanted = torch.randint(0, 256, (n, 3), generator=torch.Generator().manual_seed(1), dtype=torch.uint8)
        colour = wanted.float() / 255
        model.config.sh_degree = sh_degree
        with torch.no_grad():
            model.gauss_params["opacities"].copy_(torch.logit(opacity).unsqueeze(-1))
            dc = splatfacto.RGB2SH(colour) if sh_degree > 0 else torch.logit(colour, eps=1e-10)
            model.gauss_params["features_dc"].copy_(dc)
        xyz, rgb = model.opaque_points()
        keep = torch.arange(n) % 3 != 0
        assert xyz.shape[0] == int(keep.sum()) == n - (n + 2) // 3
        assert torch.equal(xyz, model.means.detach()[keep].cpu()) and torch.equal(rgb, wanted[keep])
    finally:
        model.config.sh_degree = saved_degree
        with torch.no_grad():
            for k, v in saved.items():
                model.gauss_params[k].copy_(v)


def test_the_option_is_named_in_the_log_and_means_nothing_without_a_restart():
    assert AfterAddConfig(restart_from="splat").describe() == "restart-from splat"
    assert not AfterAddConfig(restart_from="splat").enabled  # it acts only at restarts
