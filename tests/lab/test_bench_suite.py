"""`hpgs bench` at suite scale: suites, repeats and reference seeds, runs per GPU, provenance checked on
resume, and the paired report (which selector to use) built from the per-run JSON."""

from __future__ import annotations

import dataclasses
import json
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import REPO, require_shared
from helpers import make_result, write_rows

from hpgs_lab import provenance
from hpgs_lab.executors import ExecutorConfig, LocalExecutor, SlurmExecutor, ray_gpus_per_run, runs_per_device
from hpgs_lab.report import (
    comparison_plan,
    markdown_table,
    noise_table,
    paired_report,
    throughput_table,
    write_report,
)
from hpgs_lab.runs import Bench, out_of_memory_hint, run_settings
from hpgs_lab.suites import Scene, SuiteError, load_suite, scene_from_folder
from hpgs_ns.errors import UserError
from hpgs_ns.ns_train import SELECTION_PREFIX

# --- suites ------------------------------------------------------------------------------------------------


def test_the_shipped_suite_names_the_six_real_scenes_with_their_settings():
    root = require_shared("data")
    scenes = load_suite("real6", root)
    real = [s for s in scenes if not s.smoke]
    assert [s.name for s in real] == ["bonsai", "fox", "mold-gold-cape", "campus-building", "stitch", "juicebox"]
    assert all(s.path.is_dir() for s in real)
    fox = next(s for s in scenes if s.name == "fox")
    assert fox.dataparser == "nerfstudio-data"
    assert fox.option_dict() == {"downscale-factor": "2", "eval-mode": "interval", "eval-interval": "8"}
    assert {s.option_dict()["downscale-factor"] for s in real} == {"2"}
    assert [s.name for s in scenes if s.smoke] == ["synthetic-occluded"]


def test_real12_is_real6s_captures_then_tune6s_with_their_settings():
    root = require_shared("data")
    scenes = load_suite("real12", root)
    real6 = [s for s in load_suite("real6", root) if not s.smoke]
    assert scenes == real6 + load_suite("tune6", root)  # same folders, parsers and options; no smoke scene
    assert [s.name for s in scenes[6:]] == ["ethiopian-head", "alexander", "figurine-desk", "snowmiku-plush",
                                            "gerrard-hall", "room-lab"]
    assert all(s.path.is_dir() and (s.path / "images_2").is_dir() for s in scenes if s.name != "fox")


def test_judge13_is_real6s_captures_and_the_seven_never_tuned_and_all19_adds_tune6():
    root = require_shared("data")
    judge = load_suite("judge13", root)
    real6 = [s for s in load_suite("real6", root) if not s.smoke]
    tune = load_suite("tune6", root)
    assert judge[:6] == real6 and len(judge) == 13 and not any(s.smoke for s in judge)
    assert [s.name for s in judge[6:]] == ["gum-jar", "kumamon-plush", "helmet-chair", "ultraman-figure",
                                           "guitar-floor", "innovlab-drone", "desk-setup-ff"]
    assert not {s.name for s in judge} & {s.name for s in tune}  # never a tuning scene
    for scene in judge[6:]:  # only images_2/ there: read at factor 2
        assert scene.option_dict() == {"downscale-factor": "2"} and (scene.path / "images_2").is_dir()
        assert not (scene.path / "images").exists()
    assert load_suite("all19", root) == judge + tune


def test_suite_errors_are_one_line(tmp_path):
    with pytest.raises(SuiteError, match="unknown suite 'nope'; choose one of all19, judge13, real12, real6, tune6 or"):
        load_suite("nope")
    with pytest.raises(SuiteError, match=r"scene 'bonsai': .* does not exist; pass --data-root DIR"):
        load_suite("real6", tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text("[[scene]]\nname = 'a'\npath = 'synthetic:ring'\n[[scene]]\nname = 'a'\npath = 'synthetic:ring'\n")
    with pytest.raises(SuiteError, match="two scenes are called 'a'"):
        load_suite(str(bad))
    bad.write_text("[[scene]\n")
    with pytest.raises(SuiteError, match="not valid TOML"):
        load_suite(str(bad))


def test_jobs_run_seed_by_seed_with_repeats_and_one_reference_seed(tmp_path):
    scenes = [Scene("a", tmp_path), Scene("b", tmp_path)]
    bench = Bench(out=tmp_path, selectors=["random", "fisher"], seeds=[0, 1], reference_seeds=[0], repeats=2,
                  protocols=["fisherrf"])
    jobs = bench.jobs(scenes)
    names = [(j.seed, j.scene.name, j.name, j.repeat) for j in jobs]
    assert names[:6] == [(0, "a", "random", 0), (0, "a", "random", 1), (0, "a", "fisher", 0), (0, "a", "fisher", 1),
                         (0, "a", "initial", 0), (0, "a", "all", 0)]
    assert len(jobs) == 2 * (2 * 2 * 2 + 2)  # 2 scenes x (2 seeds x 2 selectors x 2 repeats + references once)
    assert not [j for j in jobs if j.name in ("initial", "all") and j.seed != 0]
    assert jobs[1].result_path(tmp_path) == tmp_path / "a" / "fisherrf" / "random" / "seed0-repeat1.json"


# --- runs per GPU ------------------------------------------------------------------------------------------


def test_runs_per_gpu_packs_each_gpu(monkeypatch):
    monkeypatch.setattr("hpgs_lab.executors.visible_gpus", lambda: ["3", "5"])
    lock, busy, peak = threading.Lock(), {}, {}

    def fake_run(item, env):
        gpu = env["CUDA_VISIBLE_DEVICES"]
        with lock:
            busy[gpu] = busy.get(gpu, 0) + 1
            peak[gpu] = max(peak.get(gpu, 0), busy[gpu])
        time.sleep(0.1)
        with lock:
            busy[gpu] -= 1
        return item

    done = list(LocalExecutor(ExecutorConfig(runs_per_gpu=3)).map(fake_run, range(12)))
    assert sorted(d.value for d in done) == list(range(12))
    assert peak == {"3": 3, "5": 3}  # never more than 3 on one GPU, and each GPU full
    assert runs_per_device(ExecutorConfig(runs_per_gpu=3)) == 3  # recorded with each run: its times are not its own
    assert ray_gpus_per_run(ExecutorConfig(runs_per_gpu=4)) == 0.25
    assert ray_gpus_per_run(ExecutorConfig(runs_per_gpu=4, ray_gpus_per_run=0)) == 0
    assert runs_per_device(ExecutorConfig(executor="ray", runs_per_gpu=4)) == 4


def test_without_a_gpu_runs_go_one_at_a_time(monkeypatch):
    monkeypatch.setattr("hpgs_lab.executors.visible_gpus", lambda: [])
    calls = []
    done = list(LocalExecutor(ExecutorConfig()).map(lambda item, env: calls.append(env) or item, range(3)))
    assert [d.value for d in done] == [0, 1, 2] and calls == [{}, {}, {}]  # in-process, in order
    assert runs_per_device(ExecutorConfig()) == 1


def test_runs_that_ran_out_of_gpu_memory_get_the_fix_named():
    errors = ["training failed (...):\ntorch.OutOfMemoryError: CUDA out of memory. Tried to allocate 94.00 MiB.",
              "training failed (...):\nValueError: no images", "RuntimeError: CUDA out of memory."]
    hint = out_of_memory_hint(errors, 4)
    assert hint.startswith("; 2 of them ran out of GPU memory") and "--runs-per-gpu (now 4;" in hint
    assert out_of_memory_hint(errors[1:2], 4) == ""


def test_slurm_jobs_carry_runs_per_gpu_runs_each(tmp_path):
    submitted = []

    class FakeJob:
        def __init__(self, fn, args):
            self.job_id, self.value = len(submitted), fn(*args)

        def result(self):
            return self.value

    class FakeExecutor:
        def __init__(self, folder, cluster):
            pass

        def update_parameters(self, **params):
            self.params = params

        def map_array(self, fn, *arg_lists):
            jobs = [FakeJob(fn, args) for args in zip(*arg_lists)]
            submitted.extend(jobs)
            return jobs

    executor = SlurmExecutor.__new__(SlurmExecutor)
    executor.config, executor.folder = ExecutorConfig(executor="slurm", runs_per_gpu=2, slurm_cpus_per_run=8), tmp_path
    executor.submitit = SimpleNamespace(AutoExecutor=FakeExecutor, helpers=SimpleNamespace(as_completed=lambda jobs, poll_frequency: jobs))
    done = list(executor.map(lambda item, env: (item, env["OMP_NUM_THREADS"]), list(range(5))))
    assert len(submitted) == 3  # 2 + 2 + 1
    assert sorted((d.index, d.value) for d in done) == [(i, (i, "4")) for i in range(5)]  # 8 CPUs shared by 2


# --- provenance --------------------------------------------------------------------------------------------


def test_the_code_hash_covers_the_files_the_plugin_declares(monkeypatch, tmp_path):
    import shutil

    copy = tmp_path / "hpgs_ns"
    shutil.copytree(REPO / "hpgs_ns", copy, ignore=shutil.ignore_patterns("__pycache__", "assets"))
    monkeypatch.setattr(provenance, "PACKAGE", copy)
    before = provenance.code_hash(None)
    (copy / "strategies" / "new_strategy.py").write_text("X = 1\n")  # a new module counts until declared not code
    assert provenance.code_hash(None) != before


def test_the_code_hash_follows_a_selectors_own_files_only(monkeypatch, tmp_path):
    import shutil

    copy = tmp_path / "hpgs_ns"
    shutil.copytree(REPO / "hpgs_ns", copy, ignore=shutil.ignore_patterns("__pycache__", "assets"))
    monkeypatch.setattr(provenance, "PACKAGE", copy)
    before = {s: provenance.code_hash(s) for s in ("random", "fisher", "hpgs", None)}
    assert len(set(before.values())) == 4
    (copy / "selectors" / "fisher.py").write_text((copy / "selectors" / "fisher.py").read_text() + "\nCHANGED = 1\n")
    (copy / "cli.py").write_text("# the command line cannot change a run\n")
    after = {s: provenance.code_hash(s) for s in ("random", "fisher", "hpgs", None)}
    assert [s for s in before if before[s] != after[s]] == ["fisher"]
    # comments, docstrings (the options' field docs too) and blank lines are not code
    after_add = copy / "strategies" / "restarts.py"
    text = after_add.read_text()
    assert '    """Start the splat over' in text and "# " in text
    edited = text.replace('    """Start the splat over', '    """Begin the splat again').replace(
        "import annotations", "import annotations  # a comment\n\n\n")
    after_add.write_text(edited)
    assert provenance.code_hash(None) == after[None]
    after_add.write_text(edited.replace("random_starts: bool = True", "random_starts: bool = False"))
    assert provenance.code_hash(None) != after[None]
    after_add.write_text(text)
    (copy / "model.py").write_text((copy / "model.py").read_text() + "\nCHANGED = 1\n")
    assert all(provenance.code_hash(s) != after[s] for s in after)


def test_code_text_drops_comments_and_docstrings_only():
    import textwrap

    source = textwrap.dedent('''\
        """Module doc — with a non-ASCII dash."""
        x = "# not a comment"  # a comment
        class Options:
            """Class doc."""

            steps: int = 3
            """Field doc, over
            two lines."""
            y = f"{x} — {steps}"  # after a non-ASCII string
        ''')
    path = Path(tempfile.mkdtemp()) / "m.py"
    path.write_text(source)
    assert provenance.code_text(path) == (
        'x = "# not a comment"\nclass Options:\n    steps: int = 3\n    y = f"{x} — {steps}"')


def test_resuming_with_another_preference_model_or_option_is_refused(tmp_path):
    scene = tmp_path / "scene"
    (scene / "sparse" / "0").mkdir(parents=True)
    model = tmp_path / "mine.pt"
    model.write_bytes(b"weights 1")
    bench = Bench(scenes=[scene], out=tmp_path / "out", selectors=["hpgs"], seeds=[0], references=False,
                  extra_args=f"--pipeline.selection.hpgs.model {model}")
    [job] = bench.jobs()
    settings = run_settings(bench, job)
    assert settings["selector_options"]["model"] == str(model) and settings["preference_model"] == provenance.file_hash(model)
    assert settings["code"] == provenance.code_hash("hpgs")
    path = job.result_path(bench.out)
    make_result("scene", "hpgs", "hpgs", settings=settings).to_json(path)
    bench.run_all()  # same settings: nothing to do
    model.write_bytes(b"weights 2")
    with pytest.raises(UserError, match=r"seed0.json was made with other settings \(preference_model\); pass another --out"):
        bench.run_all()
    model.write_bytes(b"weights 1")
    make_result("scene", "hpgs", "hpgs", settings={**settings, "code": "another"}).to_json(path)
    with pytest.raises(UserError, match=r"other settings \(code\); .* or --accept-code-change if"):
        bench.run_all()
    bench.accept_code_change = True
    bench.run_all()  # kept: only the code differs, and that was accepted
    make_result("scene", "hpgs", "hpgs", settings=settings).to_json(path)
    bench.extra_args += " --pipeline.selection.hpgs.batch-size 4"  # the new spelling counts as the old one did
    with pytest.raises(UserError, match=r"other settings \(extra_args, selector_options\)"):
        bench.run_all()
    assert run_settings(bench, job)["selector_options"]["batch_size"] == 4


# --- the paired report -------------------------------------------------------------------------------------


def rows(gains: dict, scenes=("s1", "s2", "s3", "s4", "s5", "s6"), seeds=(0, 1, 2), protocol="fisherrf") -> list:
    """Runs of `random` (PSNR 20 + a per-(scene, seed) offset) and of each selector at random + its gain."""
    out = []
    for i, scene in enumerate(scenes):
        for seed in seeds:
            base = 20.0 + 0.37 * i - 0.5 * seed
            for sel, gain in {"random": 0.0, **gains}.items():
                g = gain(scene) if callable(gain) else gain
                out.append(make_result(scene, protocol, sel, seed, base + g, 0.6 + g / 100, 0.3 - g / 100,
                                       num_test_views=9, num_train_views=60, num_views_final=20))
    return out


def test_primary_comparisons_are_fixed_before_the_gains():
    data = rows({"farthest": 0.2, "fisher": 0.4, "hpgs": 0.1})
    primary, secondary = comparison_plan(data, "fisherrf")
    # each against random and against farthest (the issue-47 plan), whatever the gains; the rest secondary
    assert primary == [("farthest", "random"), ("fisher", "random"), ("hpgs", "random"), ("fisher", "farthest"),
                       ("hpgs", "farthest")]
    assert secondary == [("fisher", "hpgs")]


TWELVE = tuple(f"s{i}" for i in range(1, 13))


def test_the_report_ranks_only_where_the_interval_and_the_test_allow():
    shift = lambda scene: 1.0 if scene == "s1" else 0.0  # noqa: E731 - one scene only
    text = paired_report(rows({"farthest": 0.7, "fisher": shift, "hpgs": 0.0}, scenes=TWELVE))
    # raw p 2/4096 on 12 scenes; Holm over the 5 primary comparisons (3 against random, 2 against farthest) x 5
    assert "`farthest` beats `random` (`farthest` - `random` +0.70 dB, 95% CI [+0.70, +0.70], 12 scenes, p = 0.00244, primary)." in text
    assert "`farthest` beats `hpgs` (`hpgs` - `farthest` -0.70 dB" in text
    assert "`fisher` and `random` are indistinguishable here" in text
    assert "`hpgs` and `random` are indistinguishable here (`hpgs` - `random` +0.00 dB" in text
    assert "| s1 | 60 | 9 | 0, 1, 2 |" in text  # each scene's training and test views
    # on 6 scenes the smallest sign-flip p is 2/64: x 5 primary comparisons it cannot pass 0.05
    six = paired_report(rows({"farthest": 0.7, "fisher": shift, "hpgs": 0.0}))
    assert "`farthest` and `random` are indistinguishable here (`farthest` - `random` +0.70 dB, 95% CI [+0.70, +0.70], 6 scenes)." in six
    assert "| farthest vs random | PSNR | 6 | 18 | +0.70 | [+0.70, +0.70] | 0.156 (primary, Holm; raw 0.0312) |" in six


def test_a_protocol_without_random_still_gets_its_paired_comparisons():
    # The HP-GS protocol was run with `blend` and `farthest` only: their paired interval must reach the README.
    data = [r for r in rows({"farthest": 0.0, "blend": -0.1}, scenes=("s1", "s2", "s3"), protocol="hpgs")
            if r.selector != "random"]
    assert comparison_plan(data, "hpgs") == ([("blend", "farthest")], [])
    text = paired_report(data)
    assert "#### hpgs protocol" in text
    assert "`blend` and `farthest` are indistinguishable here (`blend` - `farthest` -0.10 dB, 95% CI [-0.10, -0.10], 3 scenes)." in text
    no_baseline = [r for r in data if r.selector != "farthest"] + [
        make_result(r.scene, "hpgs", "condorcet", r.seed, r.test.psnr + 0.2) for r in data if r.selector == "blend"]
    assert comparison_plan(no_baseline, "hpgs") == ([], [("condorcet", "blend")])
    assert "every comparison is Holm-adjusted" in paired_report(no_baseline)
    assert "over `random`, per scene" not in text


def test_smoke_scenes_repeats_and_stress_copies_stay_out_of_the_comparison():
    data = rows({"farthest": 0.7})
    # a smoke scene where farthest loses 9 dB, repeats at 0 dB, a stress copy where it loses 5 dB: none counts
    data += [dataclasses.replace(r, scene="synthetic-occluded", smoke=True,
                                 test=dataclasses.replace(r.test, psnr=r.test.psnr - 9 * (r.selector == "farthest")))
             for r in rows({"farthest": 0.0}, scenes=("x",))]
    data += [dataclasses.replace(r, repeat=1, test=dataclasses.replace(r.test, psnr=0.0)) for r in rows({"farthest": 0.7})]
    data += [dataclasses.replace(r, scene="s1+exposure") for r in rows({"farthest": -5.0}, scenes=("s1",))]
    assert "+0.70 dB, 95% CI [+0.70, +0.70], 6 scenes" in paired_report(data)


def test_noise_and_throughput_tables():
    # SD over repeats 20, 20.1 of each seed: 0.0707; over seeds 20, 21, 22: 1.00
    data = [make_result("a", "p", "random", s, 20 + s + 0.1 * r, repeat=r) for s in (0, 1, 2) for r in (0, 1)]
    assert "| a | p | random | 0, 1, 2 | 2 | 0.07 | 3 | 1.00 |" in noise_table(data)
    # One seed repeated, its repeat listed first (as a glob sorts seed0-repeat1.json before seed0.json): the seed
    # spread still compares repeat 0 of each seed.
    one = [make_result("b", "p", "farthest", s, v, repeat=r) for s, r, v in ((0, 1, 20.70), (0, 0, 20.59), (1, 0, 20.78))]
    assert "| b | p | farthest | 0 | 2 | 0.08 | 2 | 0.13 |" in noise_table(one)
    assert noise_table(data[::2]) == ""  # no repeats, no table
    h100 = "NVIDIA H100 80GB HBM3"
    # 4 runs of 396 s started 1 s apart: a 399 s span, 3600 * 4 / 399 = 36.1 runs per hour
    runs = [make_result(device=h100, runs_per_gpu=4, sweep_id="x", started_at=100.0 + k, wall=396.0) for k in range(4)]
    assert "| H100 | – | 4 | 4 | 399 | 36.1 | 396 |" in throughput_table(runs)
    # Two sweeps on one machine at the same time (3 and 4 runs per GPU): one span, 7 at once, not two rows.
    shared = [make_result(device=h100, runs_per_gpu=n, sweep_id=f"vm-500.{pid}", started_at=500.0, wall=900.0)
              for pid, n in ((11, 3),) * 3 + ((12, 4),) * 4]
    table = throughput_table(runs + shared)
    assert "| H100 | – | 7 | 7 | 900 | 28.0 | 900 |" in table and table.count("| H100 |") == 2
    # The same hour on one host: 8 runs on GPU 0 without MPS, 8 on GPU 1 seen under MPS: two spans, not 16 at once.
    side = [make_result(device=h100, runs_per_gpu=8, sweep_id=f"vm-900.{g}", started_at=900.0, wall=w, gpu=g, mps=m)
            for g, m, w in (("0", None, 1000.0), ("GPU-1a2b", True, 400.0)) for _ in range(8)]
    table = throughput_table(side)
    assert "| H100 | – | 8 | 8 | 1000 | 28.8 | 1000 |" in table and "| H100 | yes | 8 | 8 | 400 | 72.0 | 400 |" in table
    mixed = side[8:15] + [make_result(device=h100, runs_per_gpu=8, sweep_id="vm-900.x", started_at=900.0, wall=400.0,
                                      gpu="GPU-1a2b", mps=False)]
    assert "| H100 | yes | 7 |" in throughput_table(mixed) and "| H100 | no | 1 |" in throughput_table(mixed)


def test_timing_columns_take_only_runs_that_had_the_gpu_to_themselves():
    run = lambda sel, sweep, start, wall: make_result(  # noqa: E731
        "a", "hpgs", sel, 0, 20.0, 0.5, 0.3, num_views_final=27, device="NVIDIA H100 80GB HBM3", sweep_id=sweep,
        started_at=start, wall=wall, selection=wall / 100)
    # `blend`'s run was a sweep of one, but another sweep's run shared the GPU with it: no solo time.
    shared = [run("blend", "vm-9.1", 0.0, 1000.0), run("farthest", "vm-9.2", 500.0, 1000.0)]
    assert "| a | hpgs | blend | 1 | 27 | 20.00 | 0.500 | 0.300 | H100 | – | – |" in markdown_table(shared)
    alone = [run("blend", "vm-9.1", 0.0, 400.0), run("farthest", "vm-9.2", 500.0, 300.0)]
    assert "| a | hpgs | blend | 1 | 27 | 20.00 | 0.500 | 0.300 | H100 | 400 | 4.0 |" in markdown_table(alone)
    other_machine = [run("blend", "vm-9.1", 0.0, 1000.0), run("farthest", "gpu2-9.2", 500.0, 1000.0)]
    assert "| H100 | 1000 | 10.0 |" in markdown_table(other_machine)


def test_report_only_writes_the_results_page(tmp_path):
    out = tmp_path / "suite"
    write_rows(out, rows({"farthest": 0.7, "fisher": 0.1}, scenes=TWELVE, seeds=(0, 1)))
    page = tmp_path / "docs" / "results.md"
    written = write_report(out, results_page=page)
    text = page.read_text()
    assert text.startswith("# Benchmark results: which selector?\n") and page in written
    assert f"Built by `hpgs bench --out {out.as_posix()} --report-only`" in text
    assert "`farthest` beats `random` (`farthest` - `random` +0.70 dB, 95% CI [+0.70, +0.70], 12 scenes" in text
    # paired.md's body, under the page's own headings (its protocol headings one level up), and its figure linked
    body = (out / "paired.md").read_text().split("\n", 1)[1]
    assert "## By the runs (views added during training)\n\n### fisherrf protocol\n" + body in text
    assert (out / "fisherrf-paired-gains.png") in written and "](../suite/fisherrf-paired-gains.png)" in text
    assert "Throughput" not in text  # these runs recorded no start times


def test_the_report_ranks_the_selectors_by_their_runs_and_by_their_final_sets(tmp_path):
    from hpgs_lab.results import SourceRun

    out = tmp_path / "suite"
    views = {"initial_views": ["v0", "v1"], "chosen_views": ["v2"], "num_views_final": 3}
    runs = [dataclasses.replace(r, **views) for r in rows({"farthest": 0.7, "hpgs": 0.0}, scenes=TWELVE, seeds=(0,))]
    write_rows(out, runs)
    # the same views from step 0: hpgs's are 1 dB better than random's, farthest's no better (a schedule cost of 0.7)
    for r in runs:
        final = r.test.psnr + {"random": 0.0, "farthest": -0.7, "hpgs": 1.0}[r.selector]
        make_result(r.scene, r.protocol, "final-set", r.seed, final, final_set_of=SourceRun(r.selector, r.seed, 0, ["v0", "v1", "v2"]),
                    **views).to_json(out / r.scene / r.protocol / r.selector / "final-set" / f"seed{r.seed}.json")
    write_report(out)
    runs_part, views_part = (out / "paired.md").read_text().split("### By their views alone (final-sets)")
    assert "`farthest` beats `random` (`farthest` - `random` +0.70 dB" in runs_part
    assert "`farthest` beats `hpgs` (`hpgs` - `farthest` -0.70 dB" in runs_part
    assert "`hpgs` beats `random` (`hpgs` - `random` +1.00 dB" in views_part
    assert "`hpgs` beats `farthest` (`hpgs` - `farthest` +1.00 dB" in views_part
    assert "`farthest` and `random` are indistinguishable here (`farthest` - `random` +0.00 dB" in views_part


def test_the_page_lists_the_runs_and_final_sets_the_grid_lacks(tmp_path):
    from hpgs_lab.results import SourceRun

    out = tmp_path / "suite"
    views = {"initial_views": ["v0"], "chosen_views": ["v1"], "num_views_final": 2}
    runs = [dataclasses.replace(r, **views) for r in rows({"farthest": 0.5, "hpgs": 0.1}, scenes=TWELVE, seeds=(0, 1))]
    # s3 ran a third seed (for every selector but hpgs, which failed there)
    runs += [dataclasses.replace(r, **views) for r in rows({"farthest": 0.5}, scenes=("s3",), seeds=(2,))]
    runs = [r for r in runs if (r.scene, r.selector, r.seed) != ("s5", "farthest", 1)]  # stopped before it ended
    write_rows(out, runs)
    for r in runs:
        if (r.scene, r.selector, r.seed) != ("s2", "random", 0):  # its final-set failed
            source = SourceRun(r.selector, r.seed, 0, ["v0", "v1"])
            make_result(r.scene, r.protocol, "final-set", r.seed, r.test.psnr + 1, final_set_of=source,
                        **views).to_json(out / r.scene / r.protocol / r.selector / "final-set" / f"seed{r.seed}.json")
    page = tmp_path / "results.md"
    write_report(out, results_page=page)
    text = page.read_text()
    assert "## Runs not in the folder" in text
    assert "- fisherrf protocol, 2 runs missing: s3/hpgs/seed2, s5/farthest/seed1." in text
    assert "- fisherrf protocol, 1 final-set missing: s2/random/seed0." in text
    assert "s3/hpgs/seed2" in (out / "missing.md").read_text()
    # the runs that were missing arrive (here: the seed-2 row goes): the next report drops the stale missing.md
    for scene, selector, seed in (("s3", "farthest", 2), ("s3", "random", 2)):
        (out / scene / "fisherrf" / selector / f"seed{seed}.json").unlink()
        (out / scene / "fisherrf" / selector / "final-set" / f"seed{seed}.json").unlink()
    restored = next(r for r in rows({"farthest": 0.5}, scenes=("s5",), seeds=(1,)) if r.selector == "farthest")
    write_rows(out, [dataclasses.replace(restored, **views)])
    source = SourceRun("farthest", 1, 0, ["v0", "v1"])
    make_result("s5", restored.protocol, "final-set", 1, restored.test.psnr + 1, final_set_of=source,
                **views).to_json(out / "s5" / restored.protocol / "farthest" / "final-set" / "seed1.json")
    make_result("s2", "fisherrf", "final-set", 0, 21.0, final_set_of=SourceRun("random", 0, 0, ["v0", "v1"]),
                **views).to_json(out / "s2" / "fisherrf" / "random" / "final-set" / "seed0.json")
    text = write_report_page(out, page)
    assert "## Runs not in the folder\n\nNone:" in text and "runs missing" not in text and "final-set missing" not in text
    assert not (out / "missing.md").exists()
    # nothing missing: the page says so in one line
    write_rows(tmp_path / "full", rows({"farthest": 0.5}, scenes=TWELVE, seeds=(0,)))
    text = write_report_page(tmp_path / "full", tmp_path / "full.md")
    assert "## Runs not in the folder\n\nNone:" in text and "missing:" not in text


def write_report_page(out, page):
    write_report(out, results_page=page)
    return page.read_text()


def test_the_results_page_goes_where_results_page_says_and_an_empty_folder_is_one_line(tmp_path):
    out = tmp_path / "suite"
    write_rows(out, rows({"farthest": 0.7}, scenes=TWELVE, seeds=(0,)))
    Bench(out=out, report_only=True, results_page=tmp_path / "page.md").main()
    text = (tmp_path / "page.md").read_text()
    assert "`farthest` beats `random`" in text and "| s1 | 60 | 9 | 0 |" in text
    with pytest.raises(UserError, match="no results under .*empty; run a sweep first"):
        Bench(out=tmp_path / "empty", report_only=True).main()


def test_a_folder_scene_is_named_after_its_folder(tiny_scene):
    scene = scene_from_folder(tiny_scene)
    assert (scene.name, scene.dataparser, scene.options) == (tiny_scene.name, "mipnerf360", ())


@pytest.mark.shipped_model
def test_per_scene_preference_models_are_used_and_checked(tmp_path):
    from hpgs_lab.runs import train_args

    scene = tmp_path / "bonsai"  # its renders trained the shipped default
    (scene / "sparse" / "0").mkdir(parents=True)
    models = tmp_path / "loso"
    models.mkdir()
    (models / "bonsai.pt").write_bytes(b"trained without bonsai")
    bench = Bench(scenes=[scene], out=tmp_path / "out", selectors=["hpgs", "random"], seeds=[0], references=False,
                  preference_models=models)
    hpgs_job, random_job = bench.jobs()
    args = train_args(bench, hpgs_job, tmp_path)
    assert args[args.index(f"--{SELECTION_PREFIX}hpgs.model") + 1] == str((models / "bonsai.pt").resolve())
    assert f"--{SELECTION_PREFIX}hpgs.model" not in train_args(bench, random_job, tmp_path)
    settings = run_settings(bench, hpgs_job)
    assert settings["preference_model"] == provenance.file_hash(models / "bonsai.pt")
    (models / "bonsai.pt").unlink()
    (models / "garden.pt").write_bytes(b"another scene's model")
    with pytest.raises(UserError, match="no preference model .*bonsai.pt for scene 'bonsai', and the shipped default saw"):
        train_args(bench, hpgs_job, tmp_path)
    # a scene the default never saw (a tuning scene) runs the default: it is already a model trained without it
    other = tmp_path / "room-lab"
    (other / "sparse" / "0").mkdir(parents=True)
    bench = Bench(scenes=[other], out=tmp_path / "out2", selectors=["hpgs"], seeds=[0], references=False,
                  preference_models=models)
    job, = bench.jobs()
    assert f"--{SELECTION_PREFIX}hpgs.model" not in train_args(bench, job, tmp_path)
    # a folder without models (a typo) is refused, not read as "every scene falls back"
    bench.preference_models = tmp_path / "typo"
    with pytest.raises(UserError, match="--preference-models .*typo is not a folder of <scene>.pt models"):
        train_args(bench, job, tmp_path)


@pytest.mark.shipped_model
def test_a_suite_scene_the_default_model_saw_is_named_unless_per_scene_models_are_given(tmp_path):
    from hpgs_lab.runs import default_model_scenes

    scenes = [tmp_path / "bonsai", tmp_path / "kitchen"]  # bonsai's renders trained the shipped default
    for scene in scenes:
        (scene / "sparse" / "0").mkdir(parents=True)
    bench = Bench(scenes=scenes, out=tmp_path / "out", selectors=["hpgs", "random"], seeds=[0], references=False)
    assert default_model_scenes(bench, bench.jobs()) == ["bonsai"]
    assert default_model_scenes(bench, [j for j in bench.jobs() if j.name == "random"]) == []
    bench = Bench(scenes=scenes, out=tmp_path / "out", selectors=["hpgs"], seeds=[0], references=False,
                  preference_models=REPO / "benchmarks" / "results" / "pref_models")
    assert default_model_scenes(bench, bench.jobs()) == []


def test_the_leave_one_scene_out_models_never_saw_their_scene():
    import torch

    folder = REPO / "benchmarks" / "results" / "pref_models"
    suite = ["bonsai", "campus-building", "fox", "juicebox", "mold-gold-cape", "stitch"]
    assert sorted(p.stem for p in folder.glob("*.pt")) == suite
    for path in folder.glob("*.pt"):
        data = torch.load(path, map_location="cpu", weights_only=True)["meta"]["training_data"]
        assert data["held_out_scene"] == path.stem and sorted(data["oracle_scenes"] + [path.stem]) == suite


def test_per_scene_blend_weights_are_passed_and_recorded(tmp_path):
    from hpgs_lab.runs import train_args

    scenes = [tmp_path / "garden", tmp_path / "other"]
    for scene in scenes:
        (scene / "sparse" / "0").mkdir(parents=True)
    table = tmp_path / "weights.json"
    table.write_text(json.dumps({"combination_loso": {"weights": {"garden": {"farthest": 0.3, "hpgs": 0.6}}}}))
    bench = Bench(scenes=scenes, out=tmp_path / "out", selectors=["blend", "farthest"], seeds=[0], references=False,
                  blend_weights=table)
    jobs = {(j.scene.name, j.name): j for j in bench.jobs()}
    args = train_args(bench, jobs["garden", "blend"], tmp_path)
    assert args[args.index(f"--{SELECTION_PREFIX}blend.farthest-weight") + 1] == "0.3"
    assert args[args.index(f"--{SELECTION_PREFIX}blend.hpgs-weight") + 1] == "0.6"
    assert run_settings(bench, jobs["garden", "blend"])["selector_options"]["hpgs_weight"] == 0.6
    # A scene the table does not name keeps the shipped weights; other selectors get no blend flags.
    assert f"--{SELECTION_PREFIX}blend.hpgs-weight" not in train_args(bench, jobs["other", "blend"], tmp_path)
    assert run_settings(bench, jobs["other", "blend"])["selector_options"]["hpgs_weight"] == 0.432
    assert not any(a.startswith(f"--{SELECTION_PREFIX}blend") for a in train_args(bench, jobs["garden", "farthest"], tmp_path))
    table.write_text(json.dumps({"combination_loso": {"weights": {"garden": {"farthest": 0.3, "fisher": 0.6}}}}))
    with pytest.raises(UserError, match="combines farthest, fisher; blend takes farthest and hpgs"):
        train_args(bench, jobs["garden", "blend"], tmp_path)
    table.write_text("{}")
    with pytest.raises(UserError, match="is not a candidate_scores.py JSON"):
        train_args(bench, jobs["garden", "blend"], tmp_path)
