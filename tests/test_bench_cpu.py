"""`hpgs bench` on a tiny synthetic scene with the CPU rasterizer: the pipeline and the JSON schema, not numbers."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from hpgs_ns.bench.protocols import fisherrf_schedule
from hpgs_ns.bench.report import device_counts, load_results, markdown_table, work_table
from hpgs_ns.bench.runs import Bench, resolve_scenes, summed_work, train_args
from hpgs_ns.bench.suites import scene_from_folder

KEYS = {
    "scene", "protocol", "selector", "seed", "steps", "test", "psnr_per_round", "wall_seconds", "selection_seconds",
    "peak_memory_mb", "initial_views", "chosen_views", "command", "num_views_final", "device",
}


def test_fisherrf_schedule_is_train_size_times_100():
    assert fisherrf_schedule()[:6] == (400, 900, 1500, 2200, 3000, 3900)
    assert fisherrf_schedule()[-1] == 18400 and len(fisherrf_schedule()) == 16


def test_tiny_bench_writes_results_table_plots_and_resumes(tiny_scene, tmp_path):
    bench = Bench(
        scenes=[tiny_scene], out=tmp_path / "bench", selectors=["farthest"], seeds=[0], protocols=["hpgs"],
        step_scale=0.002, initial_views=6, rasterizer="cpu",
        extra_args="--pipeline.model.num-downscales 0 --pipeline.model.warmup-length 1000",
    )
    bench.main()
    rows = load_results(bench.out)
    assert sorted(r["selector"] for r in rows) == ["all", "farthest", "initial"]
    for r in rows:
        assert KEYS <= set(r), KEYS - set(r)
        assert all(math.isfinite(r["test"][k]) for k in ("psnr", "ssim", "lpips"))
        assert "ns-train" in r["command"] or "nerfstudio.scripts.train" in r["command"]
    by = {r["selector"]: r for r in rows}
    assert by["initial"]["num_views_final"] == 6 and by["initial"]["chosen_views"] == []
    assert by["all"]["num_views_final"] == 35
    # step_scale 0.002: 30 steps, a round every 4 steps, 7 rounds -> 13 views, PSNR recorded before each round
    assert by["farthest"]["num_views_final"] == 13 and len(by["farthest"]["chosen_views"]) == 7
    assert [p["num_views_before"] for p in by["farthest"]["psnr_per_round"]] == list(range(6, 13))
    assert set(by["farthest"]["chosen_views"]).isdisjoint(by["farthest"]["initial_views"])
    table = (bench.out / "table.md").read_text()
    assert table == markdown_table(rows) and "| farthest |" in table and "| cpu |" in table
    assert (bench.out / f"{tiny_scene.name}-hpgs.png").stat().st_size > 10_000
    assert (bench.out / f"{tiny_scene.name}-hpgs-cameras.png").stat().st_size > 10_000

    # A second invocation finds every run done and only rebuilds the report.
    before = {p: p.stat().st_mtime for p in bench.out.glob("*/*/*/seed*.json")}
    bench.main()
    assert {p: p.stat().st_mtime for p in bench.out.glob("*/*/*/seed*.json")} == before
    assert json.loads(next(iter(before)).read_text())["seed"] == 0

    # Other arguments into the same folder would mix runs: refused, naming the file and the fix.
    changed = dataclasses.replace(bench, extra_args=bench.extra_args + " --pipeline.model.sh-degree 1")
    with pytest.raises(SystemExit, match=r"seed0.json was made with other settings \(extra_args\); pass another --out"):
        changed.main()
    assert {p: p.stat().st_mtime for p in bench.out.glob("*/*/*/seed*.json")} == before


def test_strict_init_runs_go_to_their_own_protocol_folder(tiny_scene, tmp_path):
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["random"], seeds=[0], references=False,
                  reset_after_add=True, strict_init=True)
    [job] = bench.jobs()
    assert job.protocol.name == "hpgs-reset-strict"
    args = train_args(bench, job, tmp_path / "_runs")
    assert args[args.index("--pipeline.datamanager.strict-init") + 1] == "True"


def test_work_table_shows_what_selection_skipped():
    rounds = [{"work": {"pixels_rendered": 25.0, "pixels_full_resolution": 100.0, "pairs_differentiated": 30.0,
                        "pairs_unculled": 120.0, "backward_passes": 8.0, "views_rendered": 10.0}}] * 2
    work = summed_work(rounds)
    assert work["pixels_rendered"] == 50 and work["backward_passes"] == 16
    row = {"scene": "s", "protocol": "hpgs", "selector": "fisher", "selection_work": work, "selection_seconds": 1.5}
    table = work_table([row, {**row, "selector": "random", "selection_work": {}}])
    assert "| s | hpgs | fisher | 20 | 25% | 25% | 16 | 0 | 1.5 |" in table
    assert "random" not in table  # selectors that compute nothing have no row


def test_table_names_the_devices_behind_each_row():
    rows = [{"device": "NVIDIA H100 80GB HBM3"}, {"device": "NVIDIA H200"}, {"device": "NVIDIA H100 80GB HBM3"}]
    assert device_counts(rows) == "H100 x2, H200"
    assert device_counts([{"device": "cpu x2"}]) == "cpu"


def test_synthetic_scenes_are_generated_once_by_name(tmp_path, tiny_scene):
    scenes = lambda *paths: [scene_from_folder(Path(p)) for p in paths]  # noqa: E731
    first = resolve_scenes(scenes(tiny_scene, "synthetic:sparse-objects"), tmp_path)
    assert first[0].path == tiny_scene
    made = first[1].path
    assert made == tmp_path / "synthetic-sparse-objects" and (made / "sparse" / "0").is_dir()
    assert first[1].name == "synthetic-sparse-objects"
    assert len(list((made / "images").glob("*.png"))) == 48
    stamp = (made / "ground_truth.json").stat().st_mtime
    assert [s.path for s in resolve_scenes(scenes("synthetic:sparse-objects"), tmp_path)] == [made]
    assert (made / "ground_truth.json").stat().st_mtime == stamp  # reused, not regenerated
    with pytest.raises(SystemExit, match="unknown synthetic scene 'synthetic:cube'"):
        resolve_scenes(scenes("synthetic:cube"), tmp_path)
