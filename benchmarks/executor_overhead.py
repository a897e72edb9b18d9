"""What an executor costs per run: `hpgs bench --executor ray|slurm` against `local`, on this machine.

Two measurements, written to OUT/executor_overhead.json:
1. dispatch: N trivial items (the worker returns at once) through each executor's `map`; seconds per item once
   the executor is up, and the one-off start-up (a local Ray cluster, or nothing).
2. runs: the same tiny CPU bench runs (15 steps on the 64x48 ring scene; ns-train evaluates in-process) one at a time with
   `local` and with Ray on a 1-CPU local cluster; the per-run difference of the driver's wall time.

    OMP_NUM_THREADS=1 python benchmarks/executor_overhead.py [--out benchmarks/results] [--items 20] [--runs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path


def trivial(item, env):
    return item


def dispatch(executor, items: int) -> float:
    start = time.perf_counter()
    done = list(executor.map(trivial, range(items)))
    assert sorted(d.value for d in done) == list(range(items))
    return (time.perf_counter() - start) / items


def sweep_seconds(scene: Path, out: Path, runs: int, cluster) -> dict:
    from hpgs_lab.results import load_results
    from hpgs_lab.runs import Bench

    bench = Bench(
        scenes=[scene], out=out, selectors=["random", "farthest"][:runs], seeds=[0], protocols=["hpgs"],
        references=False, step_scale=0.001, initial_views=6, rasterizer="cpu",
        extra_args="--pipeline.model.num-downscales 0 --pipeline.model.warmup-length 1000", cluster=cluster,
    )
    start = time.perf_counter()
    bench.run_all()
    elapsed = time.perf_counter() - start
    rows = load_results(out)
    return {"seconds_per_run": elapsed / len(rows), "train_seconds_per_run": sum(r.timing.wall_seconds for r in rows) / len(rows),
            "psnr": {r.selector: r.test.psnr for r in rows}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    ap.add_argument("--items", type=int, default=20)
    ap.add_argument("--runs", type=int, default=2)
    args = ap.parse_args()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    import ray

    from hpgs_lab.executors import ExecutorConfig, LocalExecutor, RayExecutor, SlurmExecutor, start_local_ray
    from hpgs_ns.scenes.synthetic import make_scene

    tmp = Path(tempfile.mkdtemp(prefix="executor_overhead."))
    report: dict = {"machine": f"{platform.node()} cpu x{os.cpu_count()}", "omp_threads": os.environ.get("OMP_NUM_THREADS")}

    # 1. Dispatch alone.
    dispatch(LocalExecutor(ExecutorConfig()), 2)  # imports torch once
    report["dispatch_seconds_per_item"] = {"local": dispatch(LocalExecutor(ExecutorConfig()), args.items)}
    start = time.perf_counter()
    start_local_ray(ray)
    report["ray_local_cluster_start_seconds"] = time.perf_counter() - start
    ray_cfg = ExecutorConfig(executor="ray", ray_gpus_per_run=0, ray_cpus_per_run=1)
    dispatch(RayExecutor(ray_cfg), 2)  # first tasks start the worker processes
    report["dispatch_seconds_per_item"]["ray"] = dispatch(RayExecutor(ray_cfg), args.items)
    ray.shutdown()
    slurm_cfg = ExecutorConfig(executor="slurm", slurm_cluster="local", slurm_gpus_per_run=0, slurm_cpus_per_run=1)
    report["dispatch_seconds_per_item"]["slurm(submitit local)"] = dispatch(SlurmExecutor(slurm_cfg, tmp / "submitit"), 8)
    print(json.dumps(report, indent=2), flush=True)

    # 2. Whole tiny runs, one at a time: the 1-CPU Ray cluster runs one task at a time, like `local`.
    scene = make_scene(tmp / "ring", layout="ring", num_cameras=40, width=64, height=48, num_points=1500, seed=0)
    report["runs"] = {"local": sweep_seconds(scene, tmp / "local", args.runs, ExecutorConfig())}
    start_local_ray(ray, num_cpus=1)
    report["runs"]["ray"] = sweep_seconds(scene, tmp / "ray", args.runs, ray_cfg)
    ray.shutdown()
    local, on_ray = report["runs"]["local"], report["runs"]["ray"]
    assert local["psnr"] == on_ray["psnr"], "Ray changed the numbers"
    report["ray_overhead_seconds_per_run"] = on_ray["seconds_per_run"] - local["seconds_per_run"]
    report["note"] = ("runs: driver wall per run (ns-train incl. its final evaluation); on a shared machine the runs' own "
                      "variation can exceed the executor's cost, compare with dispatch_seconds_per_item")
    print(json.dumps(report, indent=2))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "executor_overhead.json").write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
