"""`hpgs bench` on a tiny synthetic scene with the CPU rasterizer: the pipeline, what a run records, and the
tables' numbers for known inputs."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
from test_bench_results import make_result

from hpgs_ns.bench.protocols import fisherrf_schedule
from hpgs_ns.bench.report import device_counts, load_results, markdown_table, work_table
from hpgs_ns.bench.report.plots import camera_centres, camera_map
from hpgs_ns.bench.results import RunResult
from hpgs_ns.bench.runs import Bench, resolve_scenes, summed_work, train_args
from hpgs_ns.bench.suites import scene_from_folder
from hpgs_ns.errors import UserError
from hpgs_ns.ns_train import SELECTION_PREFIX


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
    assert sorted(r.selector for r in rows) == ["all", "farthest", "initial"]
    for r in rows:
        assert all(math.isfinite(r.test.value(k)) for k in ("psnr", "ssim", "lpips"))
        assert (r.scene, r.protocol, r.seed, r.steps) == (tiny_scene.name, "hpgs", 0, 30)
        assert (r.data, r.dataparser) == (str(tiny_scene.resolve()), "mipnerf360")
        assert "nerfstudio.scripts.train hpgs" in r.provenance.command
        assert r.provenance.settings["steps"] == 30 and r.provenance.device.startswith("cpu")
        assert (r.num_test_views, r.num_train_views) == (5, 35)
        assert r.timing.wall_seconds > 0 and r.timing.runs_per_gpu == 1 and r.timing.sweep_id
    by = {r.selector: r for r in rows}
    assert by["initial"].num_views_final == 6 and by["initial"].chosen_views == []
    assert by["all"].num_views_final == 35
    # step_scale 0.002: 30 steps, a round every 4 steps, 7 rounds -> 13 views, PSNR recorded before each round
    farthest = by["farthest"]
    assert farthest.num_views_final == 13 and len(farthest.chosen_views) == 7
    assert [p.num_views_before for p in farthest.psnr_per_round] == list(range(6, 13))
    assert [p.step for p in farthest.psnr_per_round] == [4, 8, 12, 16, 20, 24, 28]
    assert set(farthest.chosen_views).isdisjoint(farthest.initial_views)
    assert len(farthest.timing.selection_seconds_per_round) == 7
    # the table reports each run's own numbers: one seed, so no spread
    table = (bench.out / "table.md").read_text()
    assert (f"| {tiny_scene.name} | hpgs | farthest | 1 | 13 | {farthest.test.psnr:.2f} | {farthest.test.ssim:.3f} | "
            f"{farthest.test.lpips:.3f} | cpu |") in table
    lines = [line.split(" | ")[2] for line in table.splitlines()[2:]]
    assert lines == ["farthest", "initial", "all"]  # selectors first, then the reference rows
    assert (bench.out / f"{tiny_scene.name}-hpgs.png").stat().st_size > 10_000
    assert (bench.out / f"{tiny_scene.name}-hpgs-cameras.png").stat().st_size > 10_000

    # A second invocation finds every run done and only rebuilds the report.
    before = {p: p.stat().st_mtime for p in bench.out.glob("*/*/*/seed*.json")}
    bench.main()
    assert {p: p.stat().st_mtime for p in bench.out.glob("*/*/*/seed*.json")} == before

    # Other arguments into the same folder would mix runs: refused, naming the file and the fix.
    changed = dataclasses.replace(bench, extra_args=bench.extra_args + " --pipeline.model.sh-degree 1")
    with pytest.raises(UserError, match=r"seed0.json was made with other settings \(extra_args\); pass another --out"):
        changed.main()
    assert {p: p.stat().st_mtime for p in bench.out.glob("*/*/*/seed*.json")} == before


def test_selection_options_and_datamanager_options_go_to_their_groups(tiny_scene, tmp_path):
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["fisher"], seeds=[3], protocols=["fisherrf"],
                  log_candidate_scores=True)
    jobs = {j.name: j for j in bench.jobs()}
    args = train_args(bench, jobs["fisher"], tmp_path / "_runs")

    def value(flag: str, n: int = 1):
        i = args.index(flag)
        return args[i + 1 : i + 1 + n]

    assert value(f"--{SELECTION_PREFIX}selector") == ["fisher"]
    assert value(f"--{SELECTION_PREFIX}select-at", 3) == ["400", "900", "1500"]
    assert value(f"--{SELECTION_PREFIX}max-rounds") == ["16"]
    assert value(f"--{SELECTION_PREFIX}log-candidate-scores") == ["True"]
    assert value("--pipeline.datamanager.num-initial-views") == ["4"]
    assert value("--pipeline.datamanager.initial-views") == ["fps"]
    assert value("--pipeline.datamanager.seed") == ["3"]
    # reference rows: random with no rounds, `all` from every view, and no candidate log
    all_args = train_args(bench, jobs["all"], tmp_path / "_runs")
    assert all_args[all_args.index(f"--{SELECTION_PREFIX}max-rounds") + 1] == "0"
    assert all_args[all_args.index("--pipeline.datamanager.num-initial-views") + 1] == "100000"
    assert f"--{SELECTION_PREFIX}log-candidate-scores" not in all_args


def test_strict_init_runs_go_to_their_own_protocol_folder(tiny_scene, tmp_path):
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["random"], seeds=[0], references=False,
                  reset_after_add=True, strict_init=True)
    [job] = bench.jobs()
    assert job.protocol.name == "hpgs-reset-strict"
    args = train_args(bench, job, tmp_path / "_runs")
    assert args[args.index("--pipeline.datamanager.strict-init") + 1] == "True"
    assert args[args.index(f"--{SELECTION_PREFIX}reset-after-add") + 1] == "True"


def test_work_table_shows_what_selection_skipped():
    rounds = [{"work": {"pixels_rendered": 25.0, "pixels_full_resolution": 100.0, "pairs_differentiated": 30.0,
                        "pairs_unculled": 120.0, "backward_passes": 8.0, "views_rendered": 10.0}}] * 2
    work = summed_work(rounds)
    assert work["pixels_rendered"] == 50 and work["backward_passes"] == 16
    row = make_result("s", "hpgs", "fisher", selection=1.5, selection_work=work)
    table = work_table([row, make_result("s", "hpgs", "random")])
    assert "| s | hpgs | fisher | 20 | 25% | 25% | 16 | 0 | 1.5 |" in table
    assert "random" not in table  # selectors that compute nothing have no row
    assert work_table([make_result()]) == ""


def test_table_means_and_spreads_over_seeds():
    rows = [make_result("s", "hpgs", "fisher", seed, psnr, 0.5 + 0.1 * seed, 0.3, num_views_final=27, wall=100.0 * (seed + 1))
            for seed, psnr in ((0, 20.0), (1, 22.0), (2, 21.0))]
    rows.append(make_result("s", "hpgs", "fisher", 0, 99.0, repeat=1))  # a repeat: left out
    # PSNR 21 +- 1 (sample SD), SSIM 0.6 +- 0.1, wall: the mean of the solo runs
    assert ("| s | hpgs | fisher | 3 | 27 | 21.00 ± 1.00 | 0.600 ± 0.100 | 0.300 ± 0.000 | cpu x3 | 200 | 0.0 |"
            in markdown_table(rows))


def test_table_names_the_devices_behind_each_row():
    rows = [make_result(device="NVIDIA H100 80GB HBM3"), make_result(device="NVIDIA H200"),
            make_result(device="NVIDIA H100 80GB HBM3")]
    assert device_counts(rows) == "H100 x2, H200"
    assert device_counts([make_result(device="cpu x2")]) == "cpu"


def test_the_camera_map_reads_the_scene_from_the_result_not_the_command(tiny_scene, tmp_path):
    names = sorted(camera_centres(tiny_scene))
    run = make_result("ring", "hpgs", "farthest", data=str(tiny_scene), initial_views=names[:4],
                      chosen_views=names[10:12])
    assert run.provenance.command == ""
    assert camera_map([run], tmp_path / "map.png") == tmp_path / "map.png"
    assert (tmp_path / "map.png").stat().st_size > 5_000
    moved = dataclasses.replace(run, data=str(tmp_path / "gone"))
    assert camera_map([moved], tmp_path / "none.png") is None and not (tmp_path / "none.png").exists()


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
    with pytest.raises(UserError, match="unknown synthetic scene 'synthetic:cube'"):
        resolve_scenes(scenes("synthetic:cube"), tmp_path)


def test_a_results_folder_reads_back_as_written(tmp_path):
    runs = [make_result("a", "hpgs", sel, seed, 20.0 + seed) for sel in ("random", "fisher") for seed in (0, 1)]
    for r in runs:
        r.to_json(tmp_path / r.scene / r.protocol / r.selector / f"seed{r.seed}.json")
    (tmp_path / "a" / "hpgs" / "fisher" / "seed0-candidates.jsonl.gz").write_bytes(b"")  # not a result
    back = load_results(tmp_path)
    assert [(r.selector, r.seed) for r in back] == [("fisher", 0), ("fisher", 1), ("random", 0), ("random", 1)]
    assert all(isinstance(r, RunResult) for r in back) and sorted(back, key=lambda r: (r.selector, r.seed)) == back
