"""`hpgs bench --executor local|ray|slurm` on the tiny CPU benchmark: the same numbers whatever runs them.

CPU runs with a fixed seed and one intra-op thread are bit-deterministic (the same PSNR to the last digit in
repeated runs), so Ray and submitit results must equal the local ones exactly; only timings may differ.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers import lab_commands_env

from hpgs_lab import runs
from hpgs_lab.executors import ExecutorConfig, LocalExecutor, RayExecutor, SlurmExecutor
from hpgs_lab.report import load_results, markdown_table
from hpgs_lab.results import RunResult
from hpgs_lab.runs import Bench
from hpgs_ns.errors import UserError

REPO = Path(__file__).resolve().parents[2]
# 4 runs (2 selectors x 2 seeds, no reference rows) of 15 CPU steps on the 64x48 ring scene.
TINY = dict(
    selectors=["random", "farthest"], seeds=[0, 1], protocols=["hpgs"], references=False, step_scale=0.001,
    initial_views=6, rasterizer="cpu",
    extra_args="--pipeline.model.num-downscales 0 --pipeline.model.warmup-length 1000",
)
SAME = ("scene", "protocol", "selector", "seed", "steps", "num_views_final", "initial_views", "chosen_views")


def cli(scene: Path, out: Path, *extra: str) -> list:
    """The `hpgs bench` command line for TINY."""
    return [
        sys.executable, "-m", "hpgs_ns.cli", "bench", "--scenes", str(scene), "--out", str(out),
        "--selectors", *TINY["selectors"], "--seeds", *map(str, TINY["seeds"]), "--protocols", "hpgs",
        "--no-references", "--step-scale", str(TINY["step_scale"]), "--initial-views", str(TINY["initial_views"]),
        "--rasterizer", "cpu", f"--extra-args={TINY['extra_args']}", *extra,
    ]


def env() -> dict:
    """`hpgs bench` registered as pyproject.toml declares it (this checkout is on PYTHONPATH, not installed)."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO), "RAY_USAGE_STATS_ENABLED": "0", **lab_commands_env()}


def by_run(out: Path) -> dict:
    return {(r.selector, r.seed): r for r in load_results(out)}


def assert_same_numbers(out: Path, reference: Path) -> None:
    runs, ref = by_run(out), by_run(reference)
    assert runs.keys() == ref.keys() and len(runs) == 4
    for key, r in runs.items():
        assert r.test.psnr == ref[key].test.psnr, key  # bit-identical, no tolerance needed
        assert (r.test.ssim, r.test.lpips) == (ref[key].test.ssim, ref[key].test.lpips), key
        assert [getattr(r, k) for k in SAME] == [getattr(ref[key], k) for k in SAME], key
    # The markdown table is identical but for its two timing columns.
    untimed = lambda table: [line.rsplit("|", 3)[0] for line in table.splitlines()]  # noqa: E731
    assert untimed(markdown_table(load_results(out))) == untimed(markdown_table(load_results(reference)))


@pytest.fixture(scope="module")
def local_results(tiny_scene, tmp_path_factory) -> Path:
    """The 4 runs with `--executor local`, two at a time (one thread each)."""
    out = tmp_path_factory.mktemp("local") / "bench"
    Bench(scenes=[tiny_scene], out=out, cluster=ExecutorConfig(local_workers=2), **TINY).run_all()
    rows = load_results(out)
    assert len(rows) == 4 and len({r.test.psnr for r in rows}) == 4  # 4 distinct runs, not one copied
    return out


def test_missing_packages_say_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` raise ImportError
    monkeypatch.setitem(sys.modules, "submitit", None)
    with pytest.raises(UserError, match=r"^hpgs bench: --executor ray needs Ray: pip install 'hpgs-ns\[cluster\]'$"):
        RayExecutor(ExecutorConfig(executor="ray"))
    with pytest.raises(UserError, match=r"^hpgs bench: --executor slurm needs submitit: pip install 'hpgs-ns\[cluster\]'$"):
        SlurmExecutor(ExecutorConfig(executor="slurm"), Path("unused"))


def test_local_executor_pins_one_run_per_gpu(monkeypatch):
    monkeypatch.setattr("hpgs_lab.executors.visible_gpus", lambda: ["3", "5"])
    lock, busy, seen = threading.Lock(), set(), []

    def fake_run(item, extra_env):
        gpu = extra_env["CUDA_VISIBLE_DEVICES"]
        with lock:
            assert gpu not in busy, "two runs on one GPU"
            busy.add(gpu)
            seen.append(gpu)
        time.sleep(0.05)
        with lock:
            busy.discard(gpu)
        return item * 10

    done = list(LocalExecutor(ExecutorConfig(runs_per_gpu=1)).map(fake_run, range(6)))
    assert sorted((d.index, d.value) for d in done) == [(i, 10 * i) for i in range(6)]
    assert sorted(set(seen)) == ["3", "5"] and len(seen) == 6


def test_ray_sweep_matches_local_and_resumes_after_the_driver_is_killed(local_results, tiny_scene, tmp_path):
    pytest.importorskip("ray", reason="needs Ray: pip install 'hpgs-ns[cluster]'")
    out = tmp_path / "bench"
    ray_args = ("--executor", "ray", "--ray-gpus-per-run", "0", "--ray-cpus-per-run", "1")
    with open(tmp_path / "driver.log", "w") as log:
        # Own session: the driver's local Ray cluster and its workers can be cleaned up as one group.
        driver = subprocess.Popen(cli(tiny_scene, out, *ray_args), env=env(), stdout=log, stderr=log, start_new_session=True)
        deadline = time.time() + 400
        while not list(out.glob("*/*/*/seed*.json")):
            assert driver.poll() is None, (tmp_path / "driver.log").read_text()[-3000:]
            assert time.time() < deadline, "no run finished"
            time.sleep(0.5)
        driver.kill()
        driver.wait()
    time.sleep(2)
    try:
        os.killpg(driver.pid, signal.SIGKILL)  # whatever of the sweep was still running dies with it
    except ProcessLookupError:
        pass  # Ray already took its processes down with the driver
    finished = {p: p.stat().st_mtime_ns for p in out.glob("*/*/*/seed*.json")}
    assert 1 <= len(finished) < 4
    assert not list(out.glob("*/*/*/.seed*")), "a half-written JSON was left"

    rerun = subprocess.run(cli(tiny_scene, out, *ray_args), env=env(), capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert f"{4 - len(finished)} runs to do (ray, 1 per device)" in rerun.stderr
    assert {p: p.stat().st_mtime_ns for p in finished} == finished  # finished runs were not run again
    assert_same_numbers(out, local_results)
    table = (out / "table.md").read_text()  # rebuilt after the resumed sweep: both seeds of both selectors
    assert f"| {tiny_scene.name} | hpgs | random | 2 |" in table and f"| {tiny_scene.name} | hpgs | farthest | 2 |" in table


def test_slurm_path_through_submitit_local_executor(local_results, tiny_scene, tmp_path, monkeypatch):
    pytest.importorskip("submitit", reason="needs submitit: pip install 'hpgs-ns[cluster]'")
    out = tmp_path / "bench"
    done = out / tiny_scene.name / "hpgs" / "random" / "seed1.json"
    done.parent.mkdir(parents=True)
    shutil.copy(local_results / tiny_scene.name / "hpgs" / "random" / "seed1.json", done)
    before = done.stat().st_mtime_ns
    # `nope` is no selector: with the check before launch skipped, its run fails, is reported with its log, and the
    # other run's result is kept.
    monkeypatch.setattr(runs, "check_commands", lambda *args, **kwargs: None)
    cluster = ExecutorConfig(
        executor="slurm", slurm_cluster="local", slurm_gpus_per_run=0, slurm_cpus_per_run=1, slurm_time_min=10
    )
    bench = Bench(scenes=[tiny_scene], out=out, cluster=cluster, **{**TINY, "selectors": ["random", "farthest", "nope"], "seeds": [1]})
    with pytest.raises(UserError) as failed:
        bench.run_all()
    message = str(failed.value)
    assert "\n" not in message
    assert "1 of 2 runs failed" in message and f"{tiny_scene.name}/hpgs/nope/seed1 (log: " in message
    assert (out / "_runs" / f"{tiny_scene.name}-hpgs-nope-seed1.log").resolve().as_posix() in message
    assert done.stat().st_mtime_ns == before  # skipped, not submitted
    got = RunResult.from_json(out / tiny_scene.name / "hpgs" / "farthest" / "seed1.json")
    ref = RunResult.from_json(local_results / tiny_scene.name / "hpgs" / "farthest" / "seed1.json")
    metrics = ("psnr", "psnr_std", "ssim", "lpips")
    assert [getattr(got.test, k) for k in metrics] == [getattr(ref.test, k) for k in metrics]
    assert [getattr(got, k) for k in SAME] == [getattr(ref, k) for k in SAME]
    assert list((out / "_submitit").glob("*/*_result.pkl")), "submitit wrote no job results"
