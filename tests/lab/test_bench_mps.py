"""`hpgs bench --mps`: a fake `nvidia-cuda-mps-control` on PATH records what the executor asks of it.

The fake keeps the real one's interface: `-d` starts a "daemon" (a `control` file in $CUDA_MPS_PIPE_DIRECTORY),
commands come on standard input (`get_server_list`, `get_client_list PID`, `quit`), and without a daemon it
fails as the real one does. Its clients are the processes started with its pipe folder in their environment.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hpgs_lab import mps as cuda_mps
from hpgs_lab.executors import ExecutorConfig, LocalExecutor, run_together
from hpgs_lab.report import load_results
from hpgs_lab.runs import Bench, TrainingFailed
from hpgs_ns.errors import UserError

REPO = Path(__file__).resolve().parents[2]

FAKE = r'''#!{python}
import json, os, sys
from pathlib import Path
pipe = Path(os.environ.get("CUDA_MPS_PIPE_DIRECTORY", "/tmp/nvidia-mps"))
def record(**what):
    with open(os.environ["FAKE_MPS_RECORD"], "a") as f:
        f.write(json.dumps(what) + "\n")
if sys.argv[1:] == ["-d"]:
    if os.environ.get("FAKE_MPS_FAIL"):
        print("An instance of this daemon is already running", file=sys.stderr)
        sys.exit(1)
    record(cmd="-d", pipe=str(pipe), log=os.environ.get("CUDA_MPS_LOG_DIRECTORY"),
           visible=os.environ.get("CUDA_VISIBLE_DEVICES"))
    pipe.mkdir(parents=True, exist_ok=True)
    (pipe / "control").write_text("")
    sys.exit(0)
if not (pipe / "control").exists():
    print("Cannot find MPS control daemon process", file=sys.stderr)
    sys.exit(1)
words = sys.stdin.read().split()
record(cmd=" ".join(words), pipe=str(pipe))
if words == ["quit"]:
    (pipe / "control").unlink()
elif words == ["get_server_list"]:
    print(4242)
elif words[:1] == ["get_client_list"]:
    for proc in Path("/proc").iterdir():
        try:
            environ = (proc / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if proc.name.isdigit() and b"CUDA_MPS_PIPE_DIRECTORY=" + str(pipe).encode() in environ:
            print(proc.name)
'''


@pytest.fixture
def fake_mps(tmp_path, monkeypatch) -> Path:
    """The fake on PATH (and nothing in the driver folders); returns the file it records its calls in."""
    folder = tmp_path / "bin"
    folder.mkdir()
    control = folder / cuda_mps.CONTROL
    control.write_text(FAKE.replace("{python}", sys.executable))
    control.chmod(0o755)
    record = tmp_path / "mps-calls.jsonl"
    record.touch()
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_MPS_RECORD", str(record))
    monkeypatch.delenv(cuda_mps.PIPE, raising=False)
    monkeypatch.delenv(cuda_mps.LOG, raising=False)
    monkeypatch.setattr(cuda_mps, "DEFAULT_PIPE", str(tmp_path / "default-pipe"))  # no daemon of the machine's
    return record


def calls(record: Path) -> list:
    return [json.loads(line) for line in record.read_text().splitlines()]


def env_of(item, env):
    return dict(env)


def test_own_daemon_per_sweep_its_variables_in_every_run_and_quit_after(fake_mps):
    envs = [d.value for d in LocalExecutor(ExecutorConfig(mps="on", local_workers=2)).map(env_of, range(3))]
    started = [c for c in calls(fake_mps) if c["cmd"] == "-d"]
    assert len(started) == 1  # a CPU machine: one daemon, no GPU named
    pipe, log = started[0]["pipe"], started[0]["log"]
    assert Path(pipe).name.startswith("hpgs-mps-pipe-") and Path(log).name.startswith("hpgs-mps-log-")
    assert all(e[cuda_mps.PIPE] == pipe and e[cuda_mps.LOG] == log for e in envs) and len(envs) == 3
    assert calls(fake_mps)[-1] == {"cmd": "quit", "pipe": pipe}
    assert not Path(pipe).exists() and not Path(log).exists()


@pytest.mark.parametrize("stop", [KeyboardInterrupt, RuntimeError])
def test_a_failed_or_interrupted_sweep_still_quits_its_daemon(fake_mps, stop):
    def fails(item, env):
        if item == 0:
            raise stop
        time.sleep(0.5)  # still running when the other one stops the sweep

    with pytest.raises(stop):
        for _done in LocalExecutor(ExecutorConfig(mps="on", local_workers=2)).map(fails, [0, 1]):
            pass
    assert [c["cmd"] for c in calls(fake_mps)].count("quit") == 1
    assert calls(fake_mps)[-1]["cmd"] == "quit"


def test_a_daemon_the_user_runs_is_used_and_left_running(fake_mps, tmp_path, monkeypatch):
    user_pipe = tmp_path / "user-pipe"
    subprocess.run([cuda_mps.CONTROL, "-d"], env={**os.environ, cuda_mps.PIPE: str(user_pipe)}, check=True)
    monkeypatch.setenv(cuda_mps.PIPE, str(user_pipe))
    envs = [d.value for d in LocalExecutor(ExecutorConfig(mps="on", local_workers=2)).map(env_of, range(2))]
    assert all(e[cuda_mps.PIPE] == str(user_pipe) for e in envs)
    assert [c["cmd"] for c in calls(fake_mps)] == ["-d", "get_server_list"]  # the user's start, then our look
    assert (user_pipe / "control").exists()


def test_auto_is_off_without_a_shared_gpu_and_off_is_off(fake_mps):
    for mode in ("auto", "off"):
        envs = [d.value for d in LocalExecutor(ExecutorConfig(mps=mode, local_workers=2)).map(env_of, range(2))]
        assert not any(cuda_mps.PIPE in e for e in envs)
    assert calls(fake_mps) == []
    assert cuda_mps.wanted("auto", sharing=True) and not cuda_mps.wanted("auto", sharing=False)


def test_mps_on_without_the_binary_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(cuda_mps, "DRIVER_FOLDERS", (str(tmp_path / "driver"),))
    with pytest.raises(UserError, match=r"^hpgs bench: --mps on but nvidia-cuda-mps-control is not on PATH nor in the "
                                        r"driver's folders \(.*/driver\); install .* or pass --mps off$"):
        list(LocalExecutor(ExecutorConfig(mps="on", local_workers=2)).map(env_of, range(2)))
    assert not cuda_mps.wanted("auto", sharing=True)  # auto without the binary: plain runs


def test_a_daemon_that_will_not_start_is_one_line(fake_mps, monkeypatch):
    monkeypatch.setenv("FAKE_MPS_FAIL", "1")
    with pytest.raises(UserError, match=r"^hpgs bench: the CUDA MPS daemon \(.*\) did not start \(An instance of "
                                        r"this daemon is already running\); .* or pass --mps off$"):
        list(LocalExecutor(ExecutorConfig(mps="on", local_workers=2)).map(env_of, range(2)))


def test_a_slurm_job_starts_and_quits_its_own_daemon(fake_mps):
    envs = run_together(env_of, [0, 1], {"OMP_NUM_THREADS": "4"}, "on")
    pipe = calls(fake_mps)[0]["pipe"]
    assert all(e[cuda_mps.PIPE] == pipe and e["OMP_NUM_THREADS"] == "4" for e in envs)
    assert calls(fake_mps)[-1] == {"cmd": "quit", "pipe": pipe}
    assert run_together(env_of, [0], {}, "auto") == [{}]  # one run alone: no daemon


def test_runs_ended_by_a_gpu_fault_under_mps_run_again_once(fake_mps, tiny_scene, tmp_path, monkeypatch, capsys):
    from helpers import make_result

    from hpgs_lab import runs

    tries: dict = {}

    def run_one(bench, job, env=None, sweep=None):
        tries[job.seed] = tries.get(job.seed, 0) + 1
        if tries[job.seed] == 1 and job.seed < 2:  # seeds 0 and 1 share the faulting GPU
            raise TrainingFailed("hpgs bench: training failed", "RuntimeError: CUDA error: an illegal memory access")
        if job.seed == 2:
            raise TrainingFailed("hpgs bench: training failed", "ValueError: not a GPU fault")
        return make_result("ring", "hpgs", job.name, job.seed)

    monkeypatch.setattr(runs, "run_one", run_one)
    bench = Bench(scenes=[tiny_scene], out=tmp_path / "bench", selectors=["random"], seeds=[0, 1, 2],
                  references=False, cluster=ExecutorConfig(mps="on", local_workers=3))
    with pytest.raises(UserError, match=r"1 of 3 runs failed: ring/hpgs/random/seed2 "):
        bench.run_all()
    assert tries == {0: 2, 1: 2, 2: 1}  # the two runs the fault ended ran again; the plain failure did not
    assert "a GPU fault under MPS ended 2 run(s) sharing its GPU; running them again, once" in capsys.readouterr().err
    assert sorted(r.seed for r in load_results(tmp_path / "bench")) == [0, 1]
    assert [c["cmd"] for c in calls(fake_mps)].count("quit") == 2  # each pass quit its daemon


def test_a_real_sweep_records_mps_as_observed(fake_mps, tiny_scene, tmp_path):
    """Two tiny CPU runs at once under the fake: each run's JSON says it was seen as a client of its daemon."""
    out = tmp_path / "bench"
    Bench(scenes=[tiny_scene], out=out, selectors=["farthest"], seeds=[0, 1], protocols=["hpgs"], references=False,
          step_scale=0.001, initial_views=6, rasterizer="cpu", cluster=ExecutorConfig(mps="on", local_workers=2),
          extra_args="--pipeline.model.num-downscales 0 --pipeline.model.warmup-length 1000").run_all()
    rows = load_results(out)
    assert len(rows) == 2 and all(r.timing.mps is True for r in rows)
    asked = [c["cmd"] for c in calls(fake_mps)]
    assert asked[0] == "-d" and asked[-1] == "quit" and asked.count("-d") == 1
    assert any(c.startswith("get_client_list") for c in asked)


def test_the_default_runs_per_gpu_is_12_under_mps_and_4_without(fake_mps, tmp_path, monkeypatch):
    from hpgs_lab.executors import runs_per_gpu

    assert runs_per_gpu(ExecutorConfig()) == 12  # local, auto, the binary found
    assert runs_per_gpu(ExecutorConfig(mps="off")) == 4
    assert runs_per_gpu(ExecutorConfig(mps="on", runs_per_gpu=3)) == 3
    assert runs_per_gpu(ExecutorConfig(executor="ray")) == 4  # MPS on Ray's workers is the user's to start
    assert runs_per_gpu(ExecutorConfig(executor="slurm", mps="on")) == 12
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(cuda_mps, "DRIVER_FOLDERS", ())
    assert runs_per_gpu(ExecutorConfig()) == 4  # auto without the binary: no MPS
