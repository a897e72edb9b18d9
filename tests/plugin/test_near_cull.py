"""The floater guard (`--pipeline.model.near-cull.*`, `hpgs_ns.strategies.near_cull`): Gaussians close in front of a
training-split camera (active or candidate) and wide in its image are removed at densification steps."""

from __future__ import annotations

import pytest
import torch
from conftest import model_trainer, short_config
from helpers import train_steps

from hpgs_ns.errors import OptionError
from hpgs_ns.render.footprints import PinholeViews, near_and_large
from hpgs_ns.render.front import describe_front, training_surfaces
from hpgs_ns.strategies.near_cull import NearCullConfig


def guard(model):
    """The model's floater guard."""
    return model.strategies_by_name["near-cull"]


def surfaces_of(model):
    return training_surfaces(model, guard(model).active_cameras())


def one_camera(width=100, height=80, f=100.0) -> PinholeViews:
    """A camera at the origin looking down +z (OpenCV), principal point at the image centre."""
    t = lambda v: torch.tensor([float(v)])  # noqa: E731
    return PinholeViews(torch.eye(4)[None], t(f), t(f), t(width / 2), t(height / 2), t(width), t(height))


def scene_with(extra_means, extra_scales):
    """200 small Gaussians spread over the image at depth 4 (the camera's median), then `extra` rows."""
    g = torch.Generator().manual_seed(0)
    xy = (torch.rand(200, 2, generator=g) - 0.5) * 2.0  # within +-1 at z 4: inside the 100 x 80 image
    means = torch.cat([torch.cat([xy, torch.full((200, 1), 4.0)], 1), torch.tensor(extra_means)])
    scales = torch.cat([torch.full((200, 3), 0.01), torch.tensor(extra_scales)])
    return means, scales


def test_only_gaussians_both_near_and_wide_in_some_camera_are_flagged():
    extra_means = [[0.0, 0.0, 0.3],    # near (0.3 < 0.25 x 4) and 3 x 0.05 x 100 / 0.3 = 50 px > 15: flagged
                   [0.0, 0.0, 0.3],    # near but 1 px wide: kept
                   [0.0, 0.0, 3.0],    # 3 x 0.5 x 100 / 3 = 50 px wide but at 3.0 > 1.0: kept (the background)
                   [0.0, 0.0, -0.3],   # behind the camera: kept
                   [2.0, 0.0, 0.3],    # centre at u = 717 px, 667 px beyond the edge; radius 50: out of view, kept
                   [0.2, 0.0, 0.3]]    # centre at u = 117 px (outside), radius 50 reaches in: flagged
    extra_scales = [[0.05] * 3, [0.001] * 3, [0.5] * 3, [0.05] * 3, [0.05] * 3, [0.05, 0.01, 0.01]]
    means, scales = scene_with(extra_means, extra_scales)
    flagged = near_and_large(means, scales, one_camera(), screen=0.15, depth=0.25)
    assert flagged[:200].sum() == 0
    assert flagged[200:].tolist() == [True, False, False, False, False, True]
    # a wider bound keeps the 50-px one; a deeper bound (1.0 x 4 = 4 > 3) takes the background Gaussian too
    assert near_and_large(means, scales, one_camera(), screen=0.6, depth=0.25)[200:].sum() == 0
    assert near_and_large(means, scales, one_camera(), screen=0.15, depth=1.0)[202]


def test_the_depth_bound_follows_each_cameras_own_scale():
    # the same layout 10x larger (and every Gaussian 10x wider): the same rows flagged, no scene unit enters
    means, scales = scene_with([[0.0, 0.0, 0.3], [0.0, 0.0, 3.0]], [[0.05] * 3, [0.5] * 3])
    small = near_and_large(means, scales, one_camera(), 0.15, 0.25)
    large = near_and_large(means * 10, scales * 10, one_camera(), 0.15, 0.25)
    assert small.tolist() == large.tolist() and small[200] and not small[201]


def test_a_second_camera_finds_what_the_first_cannot_see():
    # camera 2 stands at z = 10 looking back down -z (rotated 180 degrees about y): the Gaussian at z 9.7 is 0.3 in
    # front of it and wide, and behind-and-far for camera 1
    means, scales = scene_with([[0.0, 0.0, 9.7]], [[0.05] * 3])
    back = torch.eye(4)
    back[:3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0]))
    back[2, 3] = 10.0  # world z 10 -> camera z 0; world z 4 -> camera z 6
    cam = one_camera()
    two = PinholeViews(torch.stack([torch.eye(4), back]), *(torch.cat([t, t]) for t in
                                                            (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)))
    assert not near_and_large(means, scales, cam, 0.15, 0.25)[200]
    assert near_and_large(means, scales, two, 0.15, 0.25)[200]


def test_the_model_removes_what_is_near_wide_and_on_no_training_surface_with_its_optimizer_rows(tiny_scene, tmp_path):
    from hpgs_ns.render.footprints import surface_support

    trainer = model_trainer(tiny_scene, tmp_path, near_cull=NearCullConfig(screen=0.15, support=1))  # one surface keeps
    model, dm = trainer.pipeline.model, trainer.pipeline.datamanager
    views = guard(model).views
    assert views is not None and len(views) == len(dm.train_dataset)  # active + candidates
    train_steps(trainer, range(2))
    # a wide, faint Gaussian just in front of a candidate camera that the training views see through (the first
    # candidate whose spot lies on no training view's rendered surface: the ring's points come near some cameras)
    surfaces = surfaces_of(model)
    assert len(surfaces[0]) == len(dm.active) and max(d.shape[0] for d in surfaces[1]) <= 48  # the 6 active views
    c2w = dm.train_dataset.cameras.camera_to_worlds
    spots = torch.stack([c2w[c, :3, 3] - 0.05 * c2w[c, :3, 2] for c in dm.candidates]).to(model.means.device)
    floater = spots[surface_support(spots, *surfaces) == 0][0]  # 0.05 along a candidate's view (OpenGL -z)
    model.add_gaussians(floater[None], torch.full((1, 3), 200, dtype=torch.uint8), trainer.optimizers)
    with torch.no_grad():
        model.gauss_params["scales"][-1] = torch.log(torch.tensor(0.05))
        model.gauss_params["opacities"][-1] = torch.logit(torch.tensor(0.02))
    n, means = model.num_points, model.means.detach().clone()
    near = near_and_large(means, torch.exp(model.scales.detach()), views, 0.15, 0.25)
    off = surface_support(means, *surfaces_of(model)) == 0
    assert near[-1] and off[-1]  # the floater: near and wide before the candidate, on no training surface
    assert (near & ~off).any()  # some near-and-wide Gaussians are on a training view's surface: they stay
    removed = guard(model).cull(model)
    assert removed == int((near & off).sum()) and guard(model).culled == removed and model.num_points == n - removed
    assert torch.equal(model.means.detach(), means[~(near & off)])
    for name, param in model.gauss_params.items():  # optimizer state rows follow the parameters
        state = trainer.optimizers.optimizers[name].state[param]
        assert param.shape[0] == model.num_points and state["exp_avg"].shape[0] == model.num_points
    assert model.get_extra_state()["strategies"]["near-cull"]["culled"] == removed


def test_a_centre_is_on_a_surface_only_where_a_view_renders_it_there():
    from hpgs_ns.render.footprints import SURFACE_TOLERANCE, surface_support

    cam = one_camera(width=10, height=8, f=10.0)
    depth, alpha = torch.full((8, 10), 4.0), torch.ones(8, 10)
    alpha[:, :2] = 0.0  # the two left columns render nothing
    means = torch.tensor([[0.0, 0.0, 4.0],    # on the surface: kept
                          [0.0, 0.0, 5.0],    # behind it: the view cannot see it there, off
                          [0.0, 0.0, 4.0 * (1 - SURFACE_TOLERANCE) - 0.1],  # clearly in front: off
                          [-1.5, 0.0, 4.0],   # u = 1.25: over a transparent pixel: off
                          [0.0, 0.0, -1.0]])  # behind the camera, in no view: off
    assert (surface_support(means, cam, [depth], [alpha]) == 0).tolist() == [False, True, True, True, True]
    # a second view that shows the third centre on its surface keeps it
    near = torch.full((8, 10), 4.0 * (1 - SURFACE_TOLERANCE) - 0.1)
    two = PinholeViews(torch.stack([cam.viewmats[0]] * 2), *(torch.cat([t, t]) for t in
                                                             (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)))
    assert (surface_support(means, two, [depth, near], [alpha, torch.ones(8, 10)]) == 0).tolist()[2] is False


def test_surface_support_counts_the_views_that_render_a_centre_on_their_surface():
    from hpgs_ns.render.footprints import surface_support

    cam = one_camera(width=10, height=8, f=10.0)
    three = PinholeViews(torch.stack([cam.viewmats[0]] * 3), *(torch.cat([t, t, t]) for t in
                                                               (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)))
    at4, at2 = torch.full((8, 10), 4.0), torch.full((8, 10), 2.0)
    means = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    # views 1 and 2 render a surface at 4, view 3 at 2; nothing renders one at 3 (25% off 4, 50% off 2)
    support = surface_support(means, three, [at4, at4, at2], [torch.ones(8, 10)] * 3)
    assert support.tolist() == [2, 1, 0]


def test_training_culls_at_densification_steps_only_and_not_when_off(tiny_scene, tmp_path):
    for on in (True, False):
        trainer = model_trainer(tiny_scene, tmp_path / str(on), near_cull=NearCullConfig(screen=0.15 if on else 0.0))
        model = trainer.pipeline.model
        assert (guard(model).views is not None) == on
        calls = []
        guard(model).cull = lambda *_, calls=calls, model=model: calls.append(model.step) or 0
        model.strategy.refine_start_iter, model.strategy.refine_every = 2, 3  # densify at steps 3, 6, 9
        train_steps(trainer, range(11))
        assert calls == ([3, 6, 9] if on else [])


def test_the_cull_acts_at_densification_steps_and_stops_with_densification(tiny_scene, tmp_path, capsys):
    trainer = model_trainer(tiny_scene, tmp_path / "on", near_cull=NearCullConfig(screen=0.15))
    model = trainer.pipeline.model
    calls = []
    guard(model).cull = lambda *_: calls.append(model.step) or 0
    strategy = model.strategy
    strategy.refine_start_iter, strategy.refine_every, strategy.refine_stop_iter = 2, 3, 7  # densify at 3, 6
    train_steps(trainer, range(14))
    assert calls == [3, 6]
    assert trainer.pipeline.datamanager.selection_signature["near-cull"] == "0.15 0.25 support 2"
    model_trainer(tiny_scene, tmp_path / "idle", near_cull=NearCullConfig(depth=0.3))  # the capture's points: off by default
    assert ("--pipeline.model.near-cull.depth does nothing in this run: --pipeline.model.near-cull.screen is off by default for this "
            "start") in capsys.readouterr().out


def test_with_support_two_a_suspect_that_one_training_view_renders_on_its_surface_goes(tiny_scene, tmp_path, capsys):
    from hpgs_ns.render.footprints import surface_support

    trainer = model_trainer(tiny_scene, tmp_path, near_cull=NearCullConfig(screen=0.15, support=2))
    model = trainer.pipeline.model
    assert trainer.pipeline.datamanager.selection_signature["near-cull"] == "0.15 0.25 support 2"
    assert "unless 2 training views show them on their surfaces" in capsys.readouterr().out
    train_steps(trainer, range(2))
    means = model.means.detach().clone()
    near = near_and_large(means, torch.exp(model.scales.detach()), guard(model).views, 0.15, 0.25)
    support = surface_support(means, *surfaces_of(model))
    assert (near & (support == 1)).any()  # some suspects have one view's support: support 1 would keep them
    removed = guard(model).cull(model)
    assert removed == int((near & (support < 2)).sum())
    assert torch.equal(model.means.detach(), means[~(near & (support < 2))])


def test_the_signature_and_the_idle_warning_name_support_only_when_it_is_not_one(tiny_scene, tmp_path, capsys):
    one = model_trainer(tiny_scene, tmp_path / "one", near_cull=NearCullConfig(screen=0.15, support=1))
    assert one.pipeline.datamanager.selection_signature["near-cull"] == "0.15 0.25"  # as the first version wrote it
    assert "unless a training view shows them on its surface" in capsys.readouterr().out
    idle = model_trainer(tiny_scene, tmp_path / "idle", near_cull=NearCullConfig(screen=0.0, support=1))
    assert "near-cull" not in idle.pipeline.datamanager.selection_signature
    assert ("--pipeline.model.near-cull.support does nothing in this run: --pipeline.model.near-cull.screen is 0 (off)"
            in capsys.readouterr().out)


def test_unset_the_guard_is_on_for_the_active_start_and_off_for_the_capture_points(tiny_scene, tmp_path, capsys):
    from hpgs_ns.strategies.near_cull import ACTIVE_START_SCREEN

    # tiny_scene has a point cloud: `auto` starts from it, and the guard stays off
    seeded = model_trainer(tiny_scene, tmp_path / "seeded")
    assert seeded.pipeline.datamanager.seed_points_mode == "colmap"
    assert guard(seeded.pipeline.model).screen == 0.0 and guard(seeded.pipeline.model).views is None
    assert "near-cull" not in seeded.pipeline.datamanager.selection_signature
    capsys.readouterr()
    cfg = short_config(tiny_scene, tmp_path / "active", steps=12, rounds=0, seed_points="active")
    active = cfg.setup(local_rank=0, world_size=1)
    active.setup()
    model = active.pipeline.model
    assert ACTIVE_START_SCREEN == 0.15 and guard(model).screen == 0.15
    assert guard(model).views is not None and len(guard(model).views) == len(active.pipeline.datamanager.train_dataset)
    assert active.pipeline.datamanager.selection_signature["near-cull"] == "0.15 0.25 support 2"
    assert "near-cull screen 0.15 (the active start's default): at each densification step" in capsys.readouterr().out
    # 0 turns it off for that start too
    cfg = short_config(tiny_scene, tmp_path / "active-off", steps=12, rounds=0, seed_points="active")
    cfg.pipeline.model.near_cull.screen = 0.0
    off = cfg.setup(local_rank=0, world_size=1)
    off.setup()
    assert guard(off.pipeline.model).screen == 0.0 and "near-cull" not in off.pipeline.datamanager.selection_signature


def test_a_resume_across_the_guards_default_names_the_flags_that_give_the_checkpoint_back():
    from types import SimpleNamespace

    from hpgs_ns.trainer import CheckpointError, check_resume_matches

    now = {"selector": "random", "seed-points": "active", "near-cull": "0.15 0.25 support 2"}

    def resume(saved):
        check_resume_matches(SimpleNamespace(datamanager=SimpleNamespace(loaded_selection_signature=saved,
                                                                         selection_signature=now)))

    resume(dict(now))
    # an active run from before the default had no guard
    with pytest.raises(CheckpointError, match=r"near-cull: checkpoint off, now 0.15 0.25 support 2.*"
                                              r"--pipeline.model.near-cull.screen 0: the active start had no floater"):
        resume({k: v for k, v in now.items() if k != "near-cull"})
    # the guard's first version (support 1); one kept on to the end used an option 0.5 removed
    with pytest.raises(CheckpointError, match="near-cull.screen 0.15 --pipeline.model.near-cull.depth 0.25 "
                                              "--pipeline.model.near-cull.support 1\\)"):
        resume({**now, "near-cull": "0.15 0.25"})
    with pytest.raises(CheckpointError, match="trained with --pipeline.model.near-cull-to-end True, which hpgs-ns 0.5"):
        resume({**now, "near-cull": "0.15 0.25 support 2 to end"})
    # and the other way: a guarded checkpoint resumed with the guard off
    with pytest.raises(CheckpointError, match=r"near-cull: checkpoint 0.15 0.25 support 2, now off"):
        check_resume_matches(SimpleNamespace(datamanager=SimpleNamespace(
            loaded_selection_signature=now, selection_signature={k: v for k, v in now.items() if k != "near-cull"})))


@pytest.mark.parametrize("flag, value", [("screen", -0.1), ("screen", 1.0), ("depth", 0.0), ("support", 0)])
def test_values_that_make_no_sense_are_one_line_errors(flag, value):
    with pytest.raises(OptionError, match=f"--pipeline.model.near-cull.{flag} "):
        NearCullConfig(**{flag: value})


def test_the_final_eval_records_the_count_only_when_the_cull_is_on(tiny_scene, tmp_path):
    import json

    from hpgs_ns.trainer import write_final_eval

    for on in (True, False):
        trainer = model_trainer(tiny_scene, tmp_path / str(on), near_cull=NearCullConfig(screen=0.15 if on else 0.0))
        guard(trainer.pipeline.model).culled = 7 if on else 0
        data = json.loads(write_final_eval(trainer, tmp_path / f"eval-{on}.json").read_text())
        assert data.get("near_culled") == (7 if on else None)


def test_in_front_counts_what_lies_between_a_camera_and_its_median_depth():
    from hpgs_ns.render.footprints import in_front

    extra_means = [[0.0, 0.0, 0.3],    # 0.3 < 0.25 x 4 and 50 px wide: in front, large
                   [0.0, 0.0, 0.3],    # in front, 1 px wide
                   [0.0, 0.0, 3.0],    # 50 px wide but beyond 0.25 x 4: not in front
                   [0.0, 0.0, -0.3]]   # behind the camera
    means, scales = scene_with(extra_means, [[0.05] * 3, [0.001] * 3, [0.5] * 3, [0.05] * 3])
    front, large = in_front(means, scales, one_camera(), 0)
    assert front.nonzero().squeeze(1).tolist() == [200, 201] and large.nonzero().squeeze(1).tolist() == [200]
    # the bound follows the centres' median: with the 200 at depth 16, the background Gaussian at 3.0 is in front too
    means[:200, 2] = 16.0
    front, large = in_front(means, scales, one_camera(), 0)
    assert front.nonzero().squeeze(1).tolist() == [200, 201, 202] and large[202]
    # a camera that holds no centre in its image has nothing in front
    assert not in_front(means + torch.tensor([100.0, 0.0, 0.0]), scales, one_camera(), 0)[0].any()


def test_the_final_eval_says_what_lies_in_front_of_each_test_camera(tiny_scene, tmp_path):
    import json

    from hpgs_ns.trainer import write_final_eval

    trainer = model_trainer(tiny_scene, tmp_path, near_cull=NearCullConfig(screen=0.0))
    model, dm = trainer.pipeline.model, trainer.pipeline.datamanager
    train_steps(trainer, range(2))
    before = json.loads(write_final_eval(trainer, tmp_path / "before.json").read_text())["test_views"]
    assert len(before) == len(dm.eval_dataset) and all(v["front_gaussians"] >= v["front_large"] >= 0 for v in before)
    # a wide Gaussian 0.05 in front of the first test camera: one more in front of it, and wide
    c2w = dm.eval_dataset.cameras.camera_to_worlds[0]
    model.add_gaussians((c2w[:3, 3] - 0.05 * c2w[:3, 2])[None].to(model.means.device),
                        torch.full((1, 3), 200, dtype=torch.uint8), trainer.optimizers)
    with torch.no_grad():
        model.gauss_params["scales"][-1] = torch.log(torch.tensor(0.05))
        model.gauss_params["opacities"][-1] = torch.logit(torch.tensor(0.99))
    after = json.loads(write_final_eval(trainer, tmp_path / "after.json").read_text())["test_views"][0]
    assert after["front_gaussians"] == before[0]["front_gaussians"] + 1
    assert after["front_large"] == before[0]["front_large"] + 1
    # opaque and filling the view from 0.05 away: it alone covers nearly all of the image
    assert after["front_cover"] > 0.9 and all(0.0 <= v["front_cover"] <= 1.0 for v in before)
    assert after["front_large_sigma_max"] == pytest.approx(max(0.05, before[0].get("front_large_sigma_max", 0.0)))
    assert 0.0 <= after["front_large_on_two_surfaces"] <= after["front_large_on_surface"] <= 1.0
    assert set(after) >= {"front_large_in_view", "front_large_suspect"}


def test_reach_any_image_is_a_footprint_reaching_into_some_view_from_in_front():
    from hpgs_ns.render.footprints import reach_any_image

    cam = one_camera()  # 100 x 80, f 100: at depth 4 the image spans x in [-2, 2), y in [-1.6, 1.6)
    means = torch.tensor([[0.0, 0.0, 4.0],    # centre of the image
                          [2.1, 0.0, 4.0],    # just right of the image, 0.01 wide: out
                          [2.1, 0.0, 4.0],    # the same place, 0.1 wide: its 3-sigma footprint reaches in
                          [0.0, 0.0, -4.0]])  # behind the camera
    scales = torch.tensor([[0.01] * 3, [0.01] * 3, [0.1] * 3, [1.0] * 3])
    assert reach_any_image(means, scales, cam).tolist() == [True, False, True, False]
    moved = torch.eye(4)
    moved[0, 3] = -2.0  # a second camera 2 to the right (world x 2.1 -> its x 0.1): sees the second
    two = PinholeViews(torch.stack([torch.eye(4), moved]), *(torch.cat([t, t]) for t in
                                                             (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)))
    assert reach_any_image(means, scales, two).tolist() == [True, True, True, False]


def test_the_shares_in_view_and_suspect_follow_the_training_cameras_and_the_split(tiny_scene, tmp_path):
    trainer = model_trainer(tiny_scene, tmp_path, near_cull=NearCullConfig(screen=0.0))
    model, dm = trainer.pipeline.model, trainer.pipeline.datamanager
    train_steps(trainer, range(2))
    test = dm.eval_dataset.cameras
    c2w = test.camera_to_worlds[0]
    model.add_gaussians((c2w[:3, 3] - 0.05 * c2w[:3, 2])[None].to(model.means.device),
                        torch.full((1, 3), 200, dtype=torch.uint8), trainer.optimizers)
    with torch.no_grad():
        model.gauss_params["scales"][-1] = torch.log(torch.tensor(0.05))
    # the test camera itself as the only "training" view and the only split camera: the floater lies in its image
    # and is near and wide there, so every large Gaussian in front of it counts as both
    mine = describe_front(model, test[0:1], test[0:1], split=test[0:1])[0]
    assert mine["front_large"] >= 1 and mine["front_large_in_view"] == 1.0 and mine["front_large_suspect"] == 1.0
    # without a split no suspect share is written; training views that look elsewhere see a smaller share
    far = describe_front(model, test[0:1], dm.active_cameras)[0]
    assert "front_large_suspect" not in far and 0.0 <= far["front_large_in_view"] <= 1.0
