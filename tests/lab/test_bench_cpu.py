"""`hpgs bench` on a tiny synthetic scene with the CPU rasterizer: the pipeline, what a run records, and the
tables' numbers for known inputs."""

from __future__ import annotations

import dataclasses
import json
import math
import shlex
import shutil
from pathlib import Path

import pytest
from helpers import make_result

from hpgs_lab.names import FINAL_SET
from hpgs_lab.protocols import fisherrf_schedule
from hpgs_lab.report import device_counts, load_results, markdown_table, schedule_cost_table, work_table, write_report
from hpgs_lab.report.plots import camera_centres, camera_map, scene_style
from hpgs_lab.results import Provenance, RunResult, SourceRun, command_options, data_from_command, load_final_sets, start_label
from hpgs_lab.runs import Bench, Job, resolve_scenes, run_settings, summed_work, train_args
from hpgs_lab.suites import scene_from_folder
from hpgs_ns.errors import UserError
from hpgs_ns.ns_train import SELECTION_PREFIX


def test_fisherrf_schedule_is_train_size_times_100():
    assert fisherrf_schedule()[:6] == (400, 900, 1500, 2200, 3000, 3900)
    assert fisherrf_schedule()[-1] == 18400 and len(fisherrf_schedule()) == 16


@pytest.fixture(scope="module")
def tiny_bench(tiny_scene, tmp_path_factory) -> Bench:
    """One finished sweep on the tiny scene: `farthest`, the `initial` and `all` rows, and farthest's final-set."""
    bench = Bench(
        scenes=[tiny_scene], out=tmp_path_factory.mktemp("tiny") / "bench", selectors=["farthest"], seeds=[0],
        protocols=["hpgs"], step_scale=0.002, initial_views=6, rasterizer="cpu", final_set="first-seed",
        extra_args="--pipeline.model.num-downscales 0 --pipeline.model.warmup-length 1000",
    )
    bench.main()
    return bench


def test_tiny_bench_writes_results_table_plots_and_resumes(tiny_bench, tiny_scene):
    bench = tiny_bench
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
    # the two lowest-PSNR test views' renders are kept beside each result
    result = bench.out / tiny_scene.name / "hpgs" / "farthest" / "seed0.json"
    lowest = sorted(farthest.test_views, key=lambda v: v.psnr)[:2]
    assert [(w["name"], w["image"]) for w in farthest.worst_views] == [(v.name, f"seed0-worst{k}.jpg") for k, v in enumerate(lowest)]
    assert all(result.with_name(w["image"]).stat().st_size > 1000 for w in farthest.worst_views)
    # each test view's render depths come through to the result (read back from its JSON)
    assert all(0 < v.depth_p10 <= v.depth_median for v in farthest.test_views)
    # and so does what lies in front of each test camera
    assert all(v.front_gaussians is not None and v.front_gaussians >= v.front_large >= 0 for v in farthest.test_views)
    assert all(r.num_gaussians and r.num_gaussians > 100 for r in rows)  # the tiny scene starts from 1500 points
    assert all(r.near_culled is None for r in rows) and "near_culled" not in json.loads(result.read_text())  # off
    assert {r.seed_points for r in rows} == {"colmap"}  # `auto` as resolved: the tiny scene has a point cloud
    # the table reports each run's own numbers: one seed, so no spread
    table = (bench.out / "table.md").read_text()
    assert (f"| {tiny_scene.name} | hpgs | farthest | 1 | 13 | {farthest.test.psnr:.2f} | {farthest.test.ssim:.3f} | "
            f"{farthest.test.lpips:.3f} | cpu |") in table
    lines = [line.split(" | ")[2] for line in table.split("\n\n")[0].splitlines()[2:]]
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


def words_after(command: str, flag: str) -> list:
    """The words after `flag` in a recorded command, up to the next option or subcommand."""
    words = shlex.split(command)
    rest = words[words.index(flag) + 1:]
    return rest[: next((i for i, w in enumerate(rest) if w.startswith("--") or w == "mipnerf360"), len(rest))]


def test_final_set_trains_the_runs_final_views_from_step_0_and_resumes(tiny_bench, tiny_scene):
    folder = tiny_bench.out / tiny_scene.name / "hpgs"
    source = json.loads((folder / "farthest" / "seed0.json").read_text())
    final_path = folder / "farthest" / "final-set" / "seed0.json"
    final = json.loads(final_path.read_text())
    views = sorted(source["initial_views"] + source["chosen_views"])
    assert len(views) == 13 == source["num_views_final"]
    # the command: exactly the run's final views as initial views, no rounds, the run's seed, steps and settings
    command = final["provenance"]["command"]
    assert words_after(command, "--pipeline.datamanager.initial-view-names") == views
    assert words_after(command, f"--{SELECTION_PREFIX}max-rounds") == ["0"]
    assert "--pipeline.datamanager.initial-views" not in shlex.split(command)
    for flag in ("--machine.seed", "--pipeline.datamanager.seed", "--max-num-iterations", "--data",
                 "--pipeline.model.rasterizer", "--pipeline.model.warmup-length", f"--{SELECTION_PREFIX}select-every"):
        assert words_after(command, flag) == words_after(source["provenance"]["command"], flag), flag
    # the result: trained those views from step 0, and names the run it belongs to
    assert (final["selector"], final["seed"], final["steps"]) == ("final-set", 0, 30)
    assert final["final_set_of"] == {"selector": "farthest", "seed": 0, "repeat": 0, "views": views}
    assert sorted(final["initial_views"]) == views and final["chosen_views"] == [] and final["psnr_per_round"] == []
    assert final["num_views_final"] == 13 and final["provenance"]["settings"] == source["provenance"]["settings"] | {
        "code": final["provenance"]["settings"]["code"], "selector_options": None, "preference_model": None}
    assert "final-set" not in {r.selector for r in load_results(tiny_bench.out)}  # not a row of the other tables

    # resumed: the final-set is skipped like a run
    before = final_path.stat().st_mtime_ns
    tiny_bench.main()
    assert final_path.stat().st_mtime_ns == before and tiny_bench.final_set_todo() == []

    # the schedule cost in table.md: final-set - run, beside initial and all, from the JSONs
    psnr = {name: json.loads((folder / name / "seed0.json").read_text())["test"]["psnr"] for name in ("initial", "all")}
    run_psnr, final_psnr = source["test"]["psnr"], final["test"]["psnr"]
    table = (tiny_bench.out / "table.md").read_text()
    assert (f"| {tiny_scene.name} | hpgs | farthest | 1 | 13 | {run_psnr:.2f} | {final_psnr:.2f} | "
            f"{final_psnr - run_psnr:+.2f} | {psnr['initial']:.2f} | {psnr['all']:.2f} |") in table
    assert f"| hpgs | farthest | 1 | 1 | {final_psnr - run_psnr:+.2f} | n/a (1 scene) |" in table

    # the run re-run with other views: its final-set is stale, left out of the report and redone by the next sweep
    copy = tiny_bench.out.parent / "stale"
    shutil.copytree(tiny_bench.out, copy, ignore=shutil.ignore_patterns("_runs", "_scenes"))
    other = next(f"images/{p.name}" for p in sorted((tiny_scene / "images").glob("*.png")) if f"images/{p.name}" not in views
                 and p.name not in {Path(t["name"]).name for t in source["test_views"]})
    edited = {**source, "chosen_views": source["chosen_views"][:-1] + [other]}
    (copy / tiny_scene.name / "hpgs" / "farthest" / "seed0.json").write_text(json.dumps(edited))
    stale = dataclasses.replace(tiny_bench, out=copy)
    [job] = stale.final_set_todo()
    assert (job.name, job.source, job.seed) == ("final-set", "farthest", 0)
    assert list(job.views) == sorted(edited["initial_views"] + edited["chosen_views"]) != views
    assert job.result_path(copy) == copy / tiny_scene.name / "hpgs" / "farthest" / "final-set" / "seed0.json"
    assert words_after(shlex.join(train_args(stale, job, copy / "_runs")), "--pipeline.datamanager.initial-view-names") == list(job.views)
    write_report(copy)
    assert "| farthest | 1 | 13 |" not in (copy / "table.md").read_text().split("Schedule cost")[1]
    assert "1 final-set result(s) left out: their run has other views now" in (copy / "table.md").read_text()
    assert dataclasses.replace(stale, final_set="none").final_set_todo() == []


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


def test_reference_rows_alone_run_without_a_selector_run(tiny_scene, tmp_path):
    # `--seeds --reference-seeds 0 --reference-rows all`: one `all` run, seed 0, and no selector run
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["random"], seeds=[], reference_seeds=[0],
                  reference_rows=["all"], protocols=["fisherrf"])
    assert [(j.name, j.seed) for j in bench.jobs()] == [("all", 0)]
    both = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["random"], seeds=[1], reference_seeds=[0])
    assert sorted((j.name, j.seed) for j in both.jobs()) == [("all", 0), ("initial", 0), ("random", 1)]


def test_strict_init_runs_go_to_their_own_protocol_folder(tiny_scene, tmp_path):
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["random"], seeds=[0], references=False,
                  reset_after_add=True, strict_init=True)
    [job] = bench.jobs()
    assert job.protocol.name == "hpgs-reset-strict"
    args = train_args(bench, job, tmp_path / "_runs")
    assert args[args.index("--pipeline.datamanager.seed-points") + 1] == "colmap-initial"
    assert args[args.index("--pipeline.model.restarts.every-round") + 1] == "True"


def test_work_table_shows_what_selection_skipped():
    from hpgs_ns.selection.records import RoundRecord

    work = {"pixels_rendered": 25.0, "pixels_full_resolution": 100.0, "pairs_differentiated": 30.0,
            "pairs_unculled": 120.0, "backward_passes": 8.0, "views_rendered": 10.0}
    # the rounds as SelectionLog.read gives them (RoundRecords since the log is typed)
    rounds = [RoundRecord(round=k, step=20 * k, selector="fisher", chosen=["v"], chosen_indices=[k], seconds=0.5,
                          num_active=6 + k, work=work) for k in (1, 2)]
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


def test_the_scenes_table_says_which_start_each_scenes_runs_used():
    from hpgs_lab.report.tables import scenes_table

    def older(scene, command):  # a run from before `seed_points` was recorded: its command tells
        return dataclasses.replace(make_result(scene, seed=2), provenance=Provenance(command=command))

    rows = [make_result("fox", seed_points="active", num_test_views=8), make_result("fox", seed=1, seed_points="active"),
            make_result("bonsai", seed_points="colmap", num_test_views=9), make_result("bonsai", seed=1),
            older("bonsai", "python -m nerfstudio.scripts.train hpgs --pipeline.datamanager.seed-points=random"),
            older("fox", "python -m nerfstudio.scripts.train hpgs --data fox nerfstudio-data --downscale-factor 2"),
            older("juicebox", "ns-train hpgs --pipeline.datamanager.strict-init True"),
            older("stitch", "ns-train hpgs --pipeline.model.random-init True"), older("stitch", "ns-train hpgs")]
    table = scenes_table(rows)
    # before `auto` the default was colmap: a random start where the capture had no point cloud
    assert "| fox | ? | 8 | 0, 1, 2 | active, colmap (random without a point cloud) |" in table
    assert "| bonsai | ? | 9 | 0, 1, 2 | colmap, not recorded, random |" in table
    assert "| juicebox | ? | ? | 2 | colmap-initial |" in table
    assert "| stitch | ? | ? | 2 | colmap, random |" in table
    assert [start_label(m, r) for m, r in (("colmap", False), ("colmap", True), ("active", True), ("random", True), (None, False))] == [
        "colmap", "random", "active (random at step 0)", "random", None]


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


def test_a_final_set_command_names_its_views_and_runs_no_rounds(tiny_scene, tmp_path):
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["fisher"], seeds=[3], protocols=["fisherrf"],
                  references=False, log_candidate_scores=True, stop_when_gain_below=0.1)
    [run] = bench.jobs()
    job = Job(run.scene, run.protocol, FINAL_SET, 3, source="fisher", views=("images/0001.png", "images/0005.png"))
    args = train_args(bench, job, tmp_path / "_runs")
    assert words_after(shlex.join(args), "--pipeline.datamanager.initial-view-names") == ["images/0001.png", "images/0005.png"]
    assert words_after(shlex.join(args), f"--{SELECTION_PREFIX}max-rounds") == ["0"]
    assert words_after(shlex.join(args), f"--{SELECTION_PREFIX}selector") == ["random"]
    assert words_after(shlex.join(args), "--machine.seed") == ["3"]
    for absent in ("--pipeline.datamanager.initial-views", f"--{SELECTION_PREFIX}log-candidate-scores",
                   f"--{SELECTION_PREFIX}stop-when-gain-below"):
        assert absent not in args
    assert job.result_path(tmp_path) == tmp_path / tiny_scene.name / "fisherrf-stop0.1" / "fisher" / "final-set" / "seed3.json"
    assert run_settings(bench, job)["selector_options"] is None

    # which finished runs get one: --final-set first-seed takes the first of --seeds, repeat 0; all takes every run
    views = {"initial_views": ["images/0001.png"], "chosen_views": ["images/0009.png"], "num_views_final": 2}
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["random", "fisher"], seeds=[2, 5], repeats=2,
                  protocols=["hpgs"], final_set="first-seed")
    for j in bench.jobs():
        if (j.name, j.seed, j.repeat) != ("fisher", 5, 1):  # not finished yet: no final-set
            make_result(j.scene.name, "hpgs", j.name, j.seed, repeat=j.repeat, **views).to_json(j.result_path(tmp_path))
    made = lambda b: sorted((j.source, j.seed, j.repeat, j.views) for j in b.final_set_jobs())  # noqa: E731
    both = ("images/0001.png", "images/0009.png")
    assert made(bench) == [("fisher", 2, 0, both), ("random", 2, 0, both)]
    assert len(made(dataclasses.replace(bench, final_set="all"))) == 7 and made(dataclasses.replace(bench, final_set="none")) == []
    old = make_result(tiny_scene.name, "hpgs", "random", 2, num_views_final=2)  # a result that names no views
    old.to_json(bench.jobs()[0].result_path(tmp_path))
    assert made(bench) == [("fisher", 2, 0, both)]


def schedule_rows():
    """Hand-made runs, references and final-sets with known schedule costs (see the test below)."""
    views = {"initial_views": [f"v{i}" for i in range(6)], "chosen_views": ["v6", "v7"], "num_views_final": 8}
    runs, finals = [], []

    def pair(scene, sel, seed, run, final, repeat=0, smoke=False, final_views=None):
        runs.append(make_result(scene, "hpgs", sel, seed, run, repeat=repeat, smoke=smoke, **views))
        source = SourceRun(sel, seed, repeat, final_views or [f"v{i}" for i in range(8)])
        finals.append(make_result(scene, "hpgs", "final-set", seed, final, repeat=repeat, smoke=smoke,
                                  initial_views=source.views, num_views_final=8, final_set_of=source))

    pair("a", "farthest", 0, 20.0, 21.0)
    pair("a", "farthest", 1, 22.0, 23.0)
    pair("b", "farthest", 0, 18.0, 21.0)
    pair("b", "farthest", 1, 19.0, 22.0)
    pair("a", "fisher", 0, 20.5, 20.0)
    pair("smoke", "farthest", 0, 10.0, 15.0, smoke=True)
    pair("a+exposure", "farthest", 0, 15.0, 16.0)
    pair("b", "fisher", 0, 19.0, 30.0, final_views=["v0", "v9"])  # stale: the run has other views now
    pair("a", "farthest", 0, 30.0, 40.0, repeat=1)  # a repeat: left out
    refs = [make_result("a", "hpgs", "initial", 0, 17.0), make_result("a", "hpgs", "all", 0, 25.0),
            make_result("a", "hpgs", "all", 1, 26.0), make_result("b", "hpgs", "initial", 0, 16.0),
            make_result("b", "hpgs", "initial", 1, 17.0)]
    return runs + refs, finals


def test_the_schedule_cost_table_pairs_each_run_with_its_final_set(tmp_path):
    rows, finals = schedule_rows()
    out = tmp_path / "bench"
    for r in rows:
        r.to_json(out / r.scene / r.protocol / r.selector / f"seed{r.seed}{f'-repeat{r.repeat}' if r.repeat else ''}.json")
    for f in finals:
        stem = f"seed{f.seed}{f'-repeat{f.repeat}' if f.repeat else ''}"
        f.to_json(out / f.scene / f.protocol / f.final_set_of.selector / "final-set" / f"{stem}.json")
    assert sorted(load_final_sets(out), key=repr) == sorted(finals, key=repr)  # they read back as written
    assert sorted(load_results(out), key=repr) == sorted(rows, key=repr)  # and are not rows of the other tables
    page = tmp_path / "results.md"
    write_report(out, results_page=page)
    table = (out / "table.md").read_text()
    assert table.startswith(markdown_table(load_results(out)) + "\n**Schedule cost (final-set − run)**\n")  # unchanged above
    expected = [
        # scene | protocol | selector | seeds | views | run | final-set | cost (final - run, mean over seeds) | initial | all
        "| a | hpgs | farthest | 2 | 8 | 21.00 | 22.00 | +1.00 | 17.00 (1) | 25.50 |",
        "| a | hpgs | fisher | 1 | 8 | 20.50 | 20.00 | -0.50 | 17.00 | 25.00 |",
        "| a+exposure | hpgs | farthest | 1 | 8 | 15.00 | 16.00 | +1.00 | – | – |",
        "| b | hpgs | farthest | 2 | 8 | 18.50 | 21.50 | +3.00 | 16.50 | – |",
        "| smoke | hpgs | farthest | 1 | 8 | 10.00 | 15.00 | +5.00 | – | – |",
        # across scenes a and b only (no smoke, no stress copy): costs 1 and 3 -> mean 2; resampling two scenes
        # gives 1, 2 or 3 with chances 1/4, 1/2, 1/4, so the 95% interval is [1, 3]
        "| hpgs | farthest | 2 | 4 | +2.00 | [+1.00, +3.00] |",
        "| hpgs | fisher | 1 | 1 | -0.50 | n/a (1 scene) |",
        "1 final-set result(s) left out: their run has other views now",
    ]
    for line in expected:
        assert line in table and line in page.read_text(), line
    schedule = table.split("**Schedule cost (final-set − run)**")[1]
    assert "| 30.00 |" not in schedule and "| b | hpgs | fisher |" not in schedule  # the repeat, the stale pair
    assert schedule_cost_table(rows, []) == ""


def test_the_two_rankings_order_selectors_by_their_runs_and_by_their_final_sets():
    from hpgs_lab.report.schedule import SchedulePair, rankings_table

    def pair(scene, sel, seed, run, final, protocol="fisherrf"):
        views = [f"v{i}" for i in range(4)]
        r = make_result(scene, protocol, sel, seed, run, initial_views=views, chosen_views=[], num_views_final=4)
        f = make_result(scene, protocol, FINAL_SET, seed, final, initial_views=views, num_views_final=4,
                        final_set_of=SourceRun(sel, seed, 0, views))
        return SchedulePair(r, f)

    pairs = [
        # farthest: best run, worst views; hpgs: the other way round (its schedule cost is large)
        pair("a", "farthest", 0, 21.0, 21.5), pair("a", "farthest", 1, 23.0, 23.5), pair("b", "farthest", 0, 19.0, 19.2),
        pair("a", "hpgs", 0, 20.0, 23.0), pair("b", "hpgs", 0, 18.0, 21.0),
        pair("a", "random", 0, 19.0, 20.0), pair("b", "random", 0, 17.0, 18.0),
        pair("c", "random", 0, 30.0, 31.0),  # only random ran on c: not in the common scenes
        pair("a", "random", 0, 10.0, 12.0, protocol="hpgs"),  # a protocol with one selector: no ranking
    ]
    table = rankings_table(pairs)
    # farthest: scene means a 22.0/22.5, b 19.0/19.2 -> 20.50 / 20.85; hpgs 19.00 / 22.00; random 18.00 / 19.00
    assert "| fisherrf | farthest | 2 | 20.50 | 1 | 20.85 | 2 |" in table
    assert "| fisherrf | hpgs | 2 | 19.00 | 2 | 22.00 | 1 |" in table
    assert "| fisherrf | random | 2 | 18.00 | 3 | 19.00 | 3 |" in table
    assert "\n| hpgs |" not in table
    assert rankings_table(pairs[-2:]) == ""


def test_the_across_scenes_table_pools_every_selector_into_one_schedule_cost():
    from hpgs_lab.report.schedule import SchedulePair, across_scenes_table

    def pair(scene, sel, seed, cost, protocol="fisherrf"):
        views = [f"v{i}" for i in range(4)]
        r = make_result(scene, protocol, sel, seed, 20.0, initial_views=views, chosen_views=[], num_views_final=4)
        f = make_result(scene, protocol, FINAL_SET, seed, 20.0 + cost, initial_views=views, num_views_final=4,
                        final_set_of=SourceRun(sel, seed, 0, views))
        return SchedulePair(r, f)

    pairs = [pair("a", "farthest", 0, 0.5), pair("a", "farthest", 1, 0.5), pair("a", "hpgs", 0, 3.0),
             pair("b", "farthest", 0, 0.2), pair("b", "hpgs", 0, 3.0),
             pair("a", "random", 0, 1.0, protocol="hpgs")]  # one selector: no pooled row for that protocol
    table = across_scenes_table(pairs, n_boot=200)
    # per scene, every pair counts once: a (0.5 + 0.5 + 3.0) / 3 = 1.333, b (0.2 + 3.0) / 2 = 1.6 -> 1.47
    assert "| fisherrf | all selectors | 2 | 5 | +1.47 |" in table
    assert "| fisherrf | farthest | 2 | 3 | +0.35 |" in table and "| fisherrf | hpgs | 2 | 2 | +3.00 |" in table
    assert "| hpgs | all selectors |" not in table and "| hpgs | random | 1 | 1 | +1.00 | n/a (1 scene) |" in table


def test_extra_args_cannot_turn_the_viewer_on_and_a_list_option_may_end_them(tmp_path):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from hpgs_ns.ns_train import ns_train_command

    # with the viewer on, ns-train never exits: a sweep would hang on its first run
    args = ns_train_command(tmp_path, tmp_path / "out", "x", "t", 100, extra=[
        "--vis", "viewer", "--pipeline.datamanager.initial-view-names", "images/a.jpg", "images/b.jpg"],
        dataparser="mipnerf360", dataparser_options={"downscale-factor": 2})
    config = tyro.cli(AnnotatedBaseConfigUnion, args=args[3:])
    assert list(config.pipeline.datamanager.initial_view_names) == ["images/a.jpg", "images/b.jpg"]
    assert config.pipeline.datamanager.dataparser.downscale_factor == 2 and config.vis == "tensorboard"


def test_max_runs_takes_the_first_runs_and_says_how_many_are_left(tiny_scene, tmp_path, capsys):
    bench = Bench(scenes=[tiny_scene], out=tmp_path, selectors=["random"], seeds=[0, 1, 2], references=False, max_runs=2)
    jobs = bench.jobs()
    assert bench.within_max_runs(jobs, 2, "runs") == jobs[:2]
    assert "--max-runs 2: 1 runs left; run again to continue" in " ".join(capsys.readouterr().err.split())
    assert bench.within_max_runs(jobs, 0, "final-set runs") == []  # the runs used the whole budget
    assert "--max-runs 2: 3 final-set runs left" in " ".join(capsys.readouterr().err.split())
    assert bench.within_max_runs(jobs, None, "runs") == jobs and bench.within_max_runs(jobs, 5, "runs") == jobs


def test_a_recorded_command_reads_the_same_with_either_spelling_of_its_options():
    words = ["ns-train", "hpgs", "--data=scenes/fox", "--pipeline.datamanager.seed-points", "active", "nerfstudio-data",
             "--downscale-factor", "2", "--pipeline.datamanager.seed-points=colmap"]
    # the last of a repeated flag wins, as tyro reads it
    assert command_options(words) == {"--data": "scenes/fox", "--pipeline.datamanager.seed-points": "colmap",
                                      "--downscale-factor": "2"}
    assert data_from_command("ns-train hpgs --data scenes/fox nerfstudio-data") == "scenes/fox"
    assert data_from_command("ns-train hpgs --data='my scenes/fox' nerfstudio-data") == "my scenes/fox"
    assert data_from_command("ns-train hpgs --vis tensorboard") is None
    assert data_from_command("ns-train hpgs --data") is None


def test_bench_passes_the_option_and_keeps_its_results_apart(tiny_scene, tmp_path):
    import sys

    import tyro

    from hpgs_lab.runs import Bench, train_args
    from hpgs_ns.method_config import hpgs_trainer_config
    from hpgs_ns.trainer import HpgsTrainerConfig

    bench = tyro.cli(Bench, args=["--scenes", str(tiny_scene), "--protocols", "fisherrf", "--reset-after-add"])
    job = bench.jobs()[0]
    assert job.protocol.name == "fisherrf-reset" and job.protocol.select_at[:2] == (400, 900)
    assert job.result_path(bench.out).parent.parent.name == "fisherrf-reset"
    args = train_args(bench, job, tmp_path)
    assert args[:4] == [sys.executable, "-m", "nerfstudio.scripts.train", "hpgs"]
    cfg = tyro.cli(tyro.conf.FlagConversionOff[HpgsTrainerConfig], default=hpgs_trainer_config(), args=args[4:])
    assert cfg.pipeline.model.restarts.every_round is True
    plain = Bench(scenes=[tiny_scene], protocols=["fisherrf"])
    assert plain.jobs()[0].protocol.name == "fisherrf"
    assert "--pipeline.model.restarts.every-round" not in train_args(plain, plain.jobs()[0], tmp_path)


def test_twelve_scenes_in_the_gain_plot_look_each_unlike_the_others():
    styles = [tuple(sorted(scene_style(j).items())) for j in range(12)]
    assert len(set(styles)) == 12  # matplotlib's ten colours alone gave scenes 0 and 10 the same dot
    assert scene_style(0)["color"] == scene_style(10)["color"] and scene_style(0)["marker"] != scene_style(10)["marker"]
