"""`--pipeline.datamanager.seed-points`: where the splat's seed points come from (auto, colmap, colmap-initial,
active, random) and the Gaussians a round adds in `active` mode (`add_gaussians`)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from conftest import require_shared, short_config
from helpers import train_steps

import hpgs_ns.scenes.triangulate as triangulate
from hpgs_ns.datamanager import ActiveViewError


def setup_trainer(cfg):
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


@pytest.fixture
def juicebox():
    data = require_shared("data", "juicebox")
    if not (data / "images_2").is_dir():  # the parser would write it into the shared folder
        pytest.skip(f"{data / 'images_2'} not found")
    return data


def juicebox_config(data, out, **options):
    cfg = short_config(data, out, **options)
    cfg.pipeline.datamanager.dataparser.downscale_factor = 2
    return cfg


@pytest.fixture
def spy(monkeypatch):
    """The views each `triangulate_views` call was given."""
    calls = []
    original = triangulate.triangulate_views

    def recording(cameras, image_paths, indices, **options):
        calls.append(sorted(int(i) for i in indices))
        return original(cameras, image_paths, indices, **options)

    monkeypatch.setattr(triangulate, "triangulate_views", recording)
    return calls


def test_active_seeds_from_the_initial_views_only_and_a_round_adds_gaussians(juicebox, tmp_path, spy):
    cfg = juicebox_config(juicebox, tmp_path / "run", steps=3, select_at=(1,), rounds=1, initial=8, selector="random",
                          seed_points="active")
    trainer = setup_trainer(cfg)
    dm, model = trainer.pipeline.datamanager, trainer.pipeline.model
    initial = list(dm.active)
    assert spy == [initial]  # the initial views' photos, nothing else
    seeded = model.num_points
    assert 100 <= seeded < 5000  # triangulated, not the COLMAP model's points nor 50000 random ones
    trainer.train()
    record = dm.history[0]
    assert spy[1] == sorted(initial + record.chosen_indices)
    added = int(record.after_add["seed_points_added"])
    assert added > 0 and record.after_add["seed_points_seconds"] > 0
    saved = trainer.pipeline.model.num_points  # refinement is off at these steps: only the round grew the splat
    assert saved == seeded + added
    # --load-dir: the checkpoint holds the grown splat
    copy = shutil.copytree(trainer.base_dir, tmp_path / "copy")
    resume = juicebox_config(juicebox, tmp_path / "resumed", steps=3, select_at=(1,), rounds=1, initial=8, selector="random",
                             seed_points="active")
    resume.load_dir = copy / "nerfstudio_models"
    calls = len(spy)
    resumed = setup_trainer(resume)
    assert resumed.pipeline.model.num_points == saved
    # the checkpoint replaces the start and says how the splat started: the initial views are not triangulated again
    assert len(spy) == calls and resumed.pipeline.model.random_start is trainer.pipeline.model.random_start is False
    assert "start_from_checkpoint" not in vars(resume.pipeline.datamanager)  # never written to config.yml
    assert resumed.pipeline.datamanager.history[0].after_add["seed_points_added"] == added
    # ns-eval / ns-viewer load the checkpoint's splat: nothing is triangulated again
    from nerfstudio.utils.eval_utils import eval_setup

    calls = len(spy)
    cfg.save_config()
    _, pipeline, _, _ = eval_setup(trainer.base_dir / "config.yml", test_mode="test")
    assert len(spy) == calls and pipeline.model.num_points == saved


def test_active_with_too_few_matches_starts_from_random_points_with_one_line(tiny_scene, tmp_path, spy, capsys):
    cfg = short_config(tiny_scene, tmp_path, steps=1, rounds=0, seed_points="active")
    cfg.pipeline.model.num_random = 3000
    trainer = setup_trainer(cfg)
    out = capsys.readouterr()
    lines = [line for line in (out.out + out.err).splitlines() if "Seed points" in line or "triangulat" in line]
    assert len(lines) == 1, lines
    assert "points triangulated from 6 views" in lines[0] and "random points" in lines[0]
    count = int(lines[0].split("only ")[1].split()[0])
    assert count < triangulate.DEFAULT_MIN_POINTS
    assert spy == [trainer.pipeline.datamanager.active]
    assert trainer.pipeline.model.num_points == 3000  # splatfacto's random init


def test_auto_keeps_the_captures_points_and_triangulates_only_without_them(tiny_scene, tmp_path, spy, capsys):
    from hpgs_ns.scenes.colmap_model import read_points3D

    cfg = short_config(tiny_scene, tmp_path / "with", steps=1, rounds=0)
    assert cfg.pipeline.datamanager.seed_points == "auto"  # the default
    trainer = setup_trainer(cfg)
    assert spy == [] and trainer.pipeline.datamanager.seed_points_mode == "colmap"
    assert trainer.pipeline.model.num_points == len(read_points3D(tiny_scene / "sparse" / "0"))
    capsys.readouterr()
    cfg = short_config(tiny_scene, tmp_path / "without", steps=1, rounds=0)
    cfg.pipeline.datamanager.dataparser.load_3D_points = False  # a capture without a point cloud
    cfg.pipeline.model.num_random = 3000
    trainer = setup_trainer(cfg)
    dm = trainer.pipeline.datamanager
    assert spy == [dm.active] and dm.seed_points_mode == "active"  # the active-start restarts apply too
    out = " ".join((lambda o: o.out + o.err)(capsys.readouterr()).split())
    assert "the capture has no point cloud, so they are triangulated from the active views" in out
    assert trainer.pipeline.model.num_points == 3000  # the tiny scene triangulates too few: random, one line
    # --pipeline.model.random-init True asks for a random start: auto triangulates nothing, no round adds points
    cfg = short_config(tiny_scene, tmp_path / "random-init", steps=1, rounds=0)
    cfg.pipeline.datamanager.dataparser.load_3D_points = False
    cfg.pipeline.model.random_init, cfg.pipeline.model.num_random = True, 2000
    trainer = setup_trainer(cfg)
    assert len(spy) == 1 and trainer.pipeline.datamanager.seed_points_mode == "colmap"
    assert trainer.pipeline.model.num_points == 2000


def test_random_mode_is_splatfactos_random_init(tiny_scene, tmp_path):
    cfg = short_config(tiny_scene, tmp_path, steps=1, rounds=0, seed_points="random")
    cfg.pipeline.model.num_random = 2000
    model = setup_trainer(cfg).pipeline.model
    assert model.num_points == 2000
    assert float(model.means.abs().max()) <= cfg.pipeline.model.random_scale / 2


def test_add_gaussians_grows_the_splat_its_optimizers_and_strategy_state(tiny_scene, tmp_path):
    trainer = setup_trainer(short_config(tiny_scene, tmp_path, steps=10, rounds=0))
    model, optimizers = trainer.pipeline.model, trainer.optimizers.optimizers
    train_steps(trainer, range(2))
    n, k = model.num_points, 7
    before = {name: p.detach().clone() for name, p in model.gauss_params.items()}
    moments = {name: optimizers[name].state[model.gauss_params[name]]["exp_avg"].clone() for name in before}
    assert model.strategy_state["grad2d"] is not None and model.strategy_state["grad2d"].shape[0] == n
    xyz = model.means.detach()[:k] + 0.01
    rgb = torch.randint(0, 256, (k, 3), dtype=torch.uint8)
    assert model.add_gaussians(xyz, rgb, trainer.optimizers) == k
    assert model.num_points == n + k
    for name, param in model.gauss_params.items():
        assert param.shape[0] == n + k and torch.equal(param[:n].detach(), before[name])
        optimizer = optimizers[name]
        assert optimizer.param_groups[0]["params"][0] is param
        state = optimizer.state[param]
        assert torch.equal(state["exp_avg"][:n], moments[name]) and not state["exp_avg"][n:].any()
        assert state["exp_avg_sq"].shape == param.shape and not state["exp_avg_sq"][n:].any()
    assert torch.allclose(model.means[n:], xyz)
    assert torch.allclose(model.opacities[n:], torch.logit(torch.tensor(0.1)))
    assert torch.allclose(model.features_dc[n:], (rgb.float() / 255 - 0.5) / 0.28209479177387814, atol=1e-5)
    assert not model.gauss_params["features_rest"][n:].any()
    assert np.isfinite(model.scales[n:].detach().numpy()).all()
    for key in ("grad2d", "count"):
        assert model.strategy_state[key].shape[0] == n + k and not model.strategy_state[key][n:].any()
    # training goes on with the grown splat: the new Gaussians get gradients and move
    train_steps(trainer, [2])
    assert model.num_points == n + k and model.strategy_state["grad2d"].shape[0] == n + k


def test_a_restart_in_active_mode_starts_from_what_the_active_views_triangulate(juicebox, tmp_path, spy):

    cfg = juicebox_config(juicebox, tmp_path / "run", steps=3, select_at=(1,), rounds=1, initial=8, views_per_round=4,
                          selector="random", seed_points="active")
    cfg.pipeline.model.restarts.at_views = (12,)
    trainer = setup_trainer(cfg)
    dm, model = trainer.pipeline.datamanager, trainer.pipeline.model
    seeded = model.num_points
    trainer.train()
    record = dm.history[0]
    count = int(record.after_add["seed_points_restart"])
    assert record.reset and spy[1] == sorted(dm.active) and len(dm.active) == 12
    assert count > seeded  # twelve views triangulate more than the first eight
    assert "seed_points_added" not in record.after_add  # the restart's points are the whole splat
    assert model.num_points == count == model.initial_gaussians["means"].shape[0]  # no refinement at these steps


def test_seed_points_min_decides_between_triangulated_and_random_points(juicebox, tmp_path, capsys):
    cfg = juicebox_config(juicebox, tmp_path / "run", steps=1, rounds=0, initial=8, seed_points="active",
                          seed_points_min=100000)
    cfg.pipeline.model.num_random = 3000
    model = setup_trainer(cfg).pipeline.model
    out = capsys.readouterr()
    line = [x for x in (out.out + out.err).splitlines() if x.startswith("Seed points:")]
    assert len(line) == 1 and "fewer than min_points 100000" in line[0] and "seed-points-min" in line[0], line
    assert model.num_points == 3000  # splatfacto's random start, though hundreds of points were triangulated
    cfg.pipeline.datamanager.seed_points_min = 0
    with pytest.raises(ActiveViewError, match="seed-points-min 0: the fewest triangulated points"):
        setup_trainer(cfg)


def test_an_active_start_restarts_by_default_at_twice_its_views_from_their_triangulation(juicebox, tmp_path, spy, capsys):
    cfg = juicebox_config(juicebox, tmp_path / "run", steps=3, select_at=(1,), rounds=1, initial=8, views_per_round=8,
                          selector="random", seed_points="active")
    trainer = setup_trainer(cfg)
    dm, model = trainer.pipeline.datamanager, trainer.pipeline.model
    seeded = model.num_points
    assert not model.random_start and seeded >= 100  # seeded from the 8 initial views' triangulation
    out = capsys.readouterr().out
    # 32 views (4x) are out of reach of one round of 8: not announced
    assert "active seed points: the splat restarts at 16 views from" in out.replace("\n", " ")
    trainer.train()
    record = dm.history[0]
    assert record.reset and len(dm.active) == 16 and spy[-1] == sorted(dm.active)
    assert int(record.after_add["seed_points_restart"]) == model.num_points > seeded
    # a checkpoint of an active run from before active starts restarted (no such key) is not resumed with them
    from types import SimpleNamespace

    from hpgs_ns.trainer import CheckpointError, check_resume_matches

    now = dm.selection_signature
    assert now["after-add.restart-active-starts"] == "True"
    old = {k: v for k, v in now.items() if k != "after-add.restart-active-starts"}
    with pytest.raises(CheckpointError, match="after-add.restart-active-starts: checkpoint \\(unset\\), now True"):
        check_resume_matches(SimpleNamespace(datamanager=SimpleNamespace(loaded_selection_signature=old, selection_signature=now)))
    # a checkpoint from before `auto` (no seed-points key): an active one resumes under auto; a random start resumed
    # under auto, which now triangulates, is refused naming the option
    def resume(saved, current):
        check_resume_matches(SimpleNamespace(datamanager=SimpleNamespace(loaded_selection_signature=saved, selection_signature=current)))

    assert now["seed-points"] == "active"
    resume({k: v for k, v in now.items() if k != "seed-points"}, now)
    with pytest.raises(CheckpointError, match=r"seed-points: checkpoint \(unset\), now active.*"
                                              r"--pipeline.datamanager.seed-points as it was trained"):
        resume({k: v for k, v in old.items() if k != "seed-points"}, now)
    colmap_now = {**old, "seed-points": "colmap"}
    resume({k: v for k, v in old.items() if k != "seed-points"}, colmap_now)  # a colmap run under auto: unchanged


def test_without_pycolmap_a_run_that_triangulates_stops_before_training_in_one_line(tiny_scene, tmp_path, spy, monkeypatch):
    import sys

    from hpgs_ns.errors import UserError

    # An install problem must not turn an active start into a random one under its name (a GPU sweep did so silently).
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # `import pycolmap` fails as if it were not installed
    cfg = short_config(tiny_scene, tmp_path / "active", steps=3, select_at=(1,), rounds=1, selector="random", seed_points="active")
    with pytest.raises(UserError) as err:
        setup_trainer(cfg)
    message = str(err.value)
    assert "\n" not in message and "seed-points active" in message and "pip install pycolmap" in message, message
    assert "seed-points colmap" in message  # the other way out
    # auto on a capture without a point cloud triangulates too; with the capture's points it needs no pycolmap
    cfg = short_config(tiny_scene, tmp_path / "auto", steps=1, rounds=0)
    cfg.pipeline.datamanager.dataparser.load_3D_points = False
    with pytest.raises(UserError, match=r"seed-points auto on a capture without a point cloud .*pip install pycolmap"):
        setup_trainer(cfg)
    assert spy == []  # nothing was triangulated, nothing trained
    trainer = setup_trainer(short_config(tiny_scene, tmp_path / "colmap", steps=1, rounds=0))
    assert trainer.pipeline.datamanager.seed_points_mode == "colmap"
    # the triangulation itself raises rather than returning a message a caller could fall back on
    with pytest.raises(triangulate.PycolmapMissingError, match="triangulation needs pycolmap"):
        triangulate.triangulate_views(trainer.pipeline.datamanager.photo_cameras,
                                      trainer.pipeline.datamanager.train_dataset.image_filenames, [0, 1])


def test_only_points_farther_than_the_splats_own_spacing_count_as_away_from_it():
    from hpgs_ns.scenes.triangulate import away_from_splat

    grid = torch.stack(torch.meshgrid(*[torch.arange(5.0)] * 3, indexing="ij"), -1).reshape(-1, 3)  # spacing 1
    points = torch.tensor([[2.0, 2.0, 2.0], [2.4, 2.0, 2.0], [2.0, 2.0, 3.9], [10.0, 0.0, 0.0], [2.0, 2.0, 5.6]])
    # on a mean, 0.4 and 0.1 from one (closer than the spacing): not away; 8 and 1.6 from the nearest: away
    assert away_from_splat(grid, points).tolist() == [False, False, False, True, True]
    assert away_from_splat(grid[:1], points).all()  # one Gaussian has no spacing: every point is new
    assert away_from_splat(grid, torch.zeros(0, 3)).shape == (0,)
