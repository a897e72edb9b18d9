"""`hpgs suggest` on a tiny CPU run: candidate poses without photos, filtered and scored, written in the scene's
own coordinates and as a nerfstudio camera path, with a contact sheet and a map; a stock splatfacto run loads
into the plugin's model; and the failures a user can fix are one line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
import yaml
from conftest import run_training, short_config

from hpgs_ns.suggest import candidates as cand
from hpgs_ns.suggest.command import Suggest, SuggestError, load_run, suggest


@pytest.fixture(scope="module")
def run_config(tiny_scene, tmp_path_factory) -> Path:
    """A 40-step run trained on 6 views of the 40-camera ring (then 8 after two rounds)."""
    cfg = short_config(tiny_scene, tmp_path_factory.mktemp("suggest"), steps=40, every=15, rounds=2, selector="farthest")
    return Path(run_training(cfg).base_dir) / "config.yml"


@pytest.fixture(scope="module")
def run(run_config):
    return load_run(run_config)


def test_suggestions_are_written_in_both_coordinate_frames(run, run_config):
    out = suggest(run, Suggest(run_config, num=3, selector="farthest", candidates="sphere", count=64))
    folder = run_config.parent
    saved = json.loads((folder / "suggested_views.json").read_text())
    assert saved == json.loads(json.dumps(out)) and saved["num"] == 3 and saved["generated"] == 64
    assert saved["scored"] == 64 - sum(saved["dropped"].values())
    # undoing the dataparser's transform: the training cameras' own round trip gives their COLMAP poses back
    outputs = run.pipeline.datamanager.train_dataparser_outputs
    for s in saved["suggestions"]:
        c2w = torch.tensor(s["camera_to_world"])[:3]
        back = outputs.transform_poses_to_original_space(c2w[None], camera_convention="opencv")[0]
        assert torch.allclose(back, torch.tensor(s["camera_to_world_original"])[:3], atol=1e-5)
    # farthest's greedy picks: each is farther from every photo trained on than the candidates it beat
    scores = [s["score"] for s in saved["suggestions"]]
    assert scores[0] == max(scores) and len({s["candidate"] for s in saved["suggestions"]}) == 3
    path = json.loads((folder / "suggested_camera_path.json").read_text())
    assert path["render_width"] == 64 and len(path["camera_path"]) == len(path["keyframes"]) == 3
    assert path["camera_path"][0]["camera_to_world"] == sum(saved["suggestions"][0]["camera_to_world"], [])
    assert (folder / "suggestions_contact_sheet.png").stat().st_size > 5_000
    assert (folder / "suggestions_map.png").stat().st_size > 20_000


def test_a_full_ring_leaves_no_orbit_pose_and_says_so(run, run_config):
    with pytest.raises(SuggestError, match=r"no candidate pose left: of \d+ orbit poses, \d+ are within 1 x the photo spacing"):
        suggest(run, Suggest(run_config, num=2, selector="farthest", candidates="orbit"))
    out = suggest(run, Suggest(run_config, num=2, selector="fisher", candidates="orbit", count=24, min_distance=0.3))
    assert out["num"] == 2 and all(math.isfinite(s["score"]) for s in out["suggestions"])


def test_blend_suggests_distinct_poses_with_finite_scores(run, run_config):
    out = suggest(run, Suggest(run_config, num=2, selector="blend", candidates="sphere", count=32))
    assert out["selector"] == "blend" and len({s["candidate"] for s in out["suggestions"]}) == 2
    assert all(math.isfinite(s["score"]) for s in out["suggestions"])


def test_a_camera_path_file_is_read_and_its_unusable_poses_dropped(run, run_config, tmp_path):
    dm = run.pipeline.datamanager
    lay = cand.layout(dm.train_dataset.cameras.camera_to_worlds)
    photo = dm.train_dataset.cameras.camera_to_worlds[3]
    outside = cand.look_at((lay.centre + 2.5 * lay.up)[None], lay.centre, torch.tensor([1.0, 0, 0]))[0]
    middle = cand.look_at(lay.centre[None] + 0.01, lay.centre, lay.up)[0]
    rows = [torch.cat([m, torch.tensor([[0, 0, 0, 1.0]])]).reshape(-1).tolist() for m in (photo, outside, middle)]
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"camera_path": [{"camera_to_world": r, "fov": 50.0, "aspect": 4 / 3} for r in rows],
                                "render_height": 48, "render_width": 64}))
    poses, fovs = cand.from_file(path)
    assert poses.shape == (3, 3, 4) and fovs == [50.0, 50.0, 50.0]
    opacities = run.pipeline.model.gauss_params["opacities"]
    saved = opacities.detach().clone()
    opacities.data.fill_(3.0)  # a converged splat: opaque objects (40 steps leave them haze)
    try:
        out = suggest(run, Suggest(run_config, num=1, selector="hpgs", candidates=str(path)))
    finally:
        opacities.data.copy_(saved)
    assert out["dropped"]["too_close"] == 1 and out["dropped"]["inside_object"] + out["dropped"]["view_blocked"] == 1
    assert [s["candidate"] for s in out["suggestions"]] == [1] and out["suggestions"][0]["fov_deg"] == pytest.approx(50.0)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(cand.CandidateError, match="bad.json is not a camera path .*; pass a nerfstudio camera-path JSON"):
        cand.from_file(tmp_path / "bad.json")


def test_a_stock_splatfacto_run_loads_into_the_plugins_model(run_config, tmp_path):
    """The same checkpoint, described as `ns-train splatfacto` would: stock pipeline, datamanager and model."""
    import dataclasses
    import shutil

    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
    from nerfstudio.models.splatfacto import SplatfactoModelConfig
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    folder = tmp_path / "runs" / "x" / "splatfacto" / "run"
    shutil.copytree(run_config.parent, folder)
    config = yaml.load(run_config.read_text(), Loader=yaml.Loader)
    dm, model = config.pipeline.datamanager, config.pipeline.model
    stock_dm = FullImageDatamanagerConfig(data=dm.data, dataparser=dm.dataparser, cache_images="gpu")
    stock_model = SplatfactoModelConfig(**{f.name: getattr(model, f.name) for f in dataclasses.fields(SplatfactoModelConfig)})
    config.pipeline = VanillaPipelineConfig(datamanager=stock_dm, model=stock_model)
    config.method_name = "splatfacto"
    (folder / "config.yml").write_text(yaml.dump(config))
    stock = load_run(folder / "config.yml")
    assert type(stock.pipeline.model).__name__ == "HpgsSplatfactoModel" and stock.selector == "farthest"  # ns-train hpgs's default
    assert stock.trained == list(range(35))  # a splatfacto run trained on every training view
    out = suggest(stock, Suggest(folder / "config.yml", num=2, selector="farthest", candidates="sphere", count=32))
    assert out["trained_views"] == 35 and out["num"] == 2


def test_a_run_without_checkpoint_is_a_one_line_error(run_config, tmp_path):
    folder = tmp_path / "empty"
    folder.mkdir()
    (folder / "config.yml").write_text(run_config.read_text())
    with pytest.raises(SuggestError, match="has no checkpoint .*; train the run first"):
        load_run(folder / "config.yml")
    with pytest.raises(SuggestError, match="nope.yml not found; pass --load-config RUN/config.yml"):
        load_run(tmp_path / "nope.yml")


def test_excluded_views_are_never_trained_on_nor_candidates(tiny_scene, tmp_path):
    """The withheld-arc check (`benchmarks/suggest_check.py`) trains on a capture that lacks an arc."""
    excluded = [f"images/{i:04d}.png" for i in (1, 2, 3, 4, 5, 6, 7)]
    cfg = short_config(tiny_scene, tmp_path, steps=21, every=20, rounds=1, initial=100000, exclude_views=tuple(excluded))
    dm = run_training(cfg).pipeline.datamanager
    names = {dm.image_names[i] for i in dm.active} | {dm.image_names[i] for i in dm.candidates}
    assert len(dm.active) == 35 - 7 and not names & set(excluded) and dm.candidates == []
