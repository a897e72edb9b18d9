"""Where a training step's time goes: torch profiler over a window of steps of an `hpgs` run without rounds (a
final-set run), alone or as one of N runs sharing the GPU (under CUDA MPS or not).

    python benchmarks/profile_step.py --scene PATH --views-json benchmarks/results/judge-full/farthest_views.json \
        --scene-name stitch --steps 6100 --window 6000 6050 --concurrent 8 --mps on --out DIR

The parent starts an MPS daemon for the GPU (`--mps on`, `hpgs_lab.mps`), then N training processes with the
same settings; the first is profiled over `--window` (callbacks, data loading and logging included: everything
between the window's first and last step). DIR/profile.json: the window's wall time per step, the GPU's busy time
per step (union of kernel intervals) and its share of the wall time, host-device syncs per step, the top kernels
and the top CPU ops by self time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

SYNCS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy", "cudaMemcpyAsync",
         "aten::item", "aten::_local_scalar_dense", "aten::nonzero")


def summarize(prof, steps: int, wall: float) -> dict:
    from torch.autograd import DeviceType

    kernels, cpu_ops = [], {}
    syncs = {name: 0 for name in SYNCS}
    for evt in prof.events():
        if evt.device_type == DeviceType.CUDA:
            kernels.append((evt.time_range.start, evt.time_range.end, evt.name))
        else:
            if evt.name in syncs:
                syncs[evt.name] += 1
    busy, end = 0.0, -1.0
    for start, stop, _ in sorted(kernels):
        if stop <= end:
            continue
        busy += stop - max(start, end)
        end = stop
    by_kernel: dict = {}
    for start, stop, name in kernels:
        by_kernel[name] = by_kernel.get(name, 0.0) + (stop - start)
    for avg in prof.key_averages():
        if avg.device_type != DeviceType.CUDA:
            cpu_ops[avg.key] = avg.self_cpu_time_total
    top = lambda d, k: [(n, round(v / 1000 / steps, 3)) for n, v in sorted(d.items(), key=lambda kv: -kv[1])[:k]]  # noqa: E731
    return {
        "steps": steps,
        "wall_ms_per_step": round(1000 * wall / steps, 3),
        "gpu_busy_ms_per_step": round(busy / 1000 / steps, 3),
        "gpu_busy_share": round(busy / 1e6 / wall, 3),
        "kernels_per_step": round(len(kernels) / steps, 1),
        "syncs_per_step": {k: round(v / steps, 2) for k, v in syncs.items() if v},
        "top_kernels_ms_per_step": top(by_kernel, 12),
        "top_cpu_self_ms_per_step": top(cpu_ops, 15),
    }


def worker(args: argparse.Namespace) -> None:
    import torch
    from nerfstudio.scripts.train import main as train_main

    from hpgs_ns.method_config import hpgs_trainer_config
    from hpgs_ns.trainer import HpgsTrainer

    names = sorted(json.loads(args.views_json.read_text())["views"][args.scene_name])
    cfg = hpgs_trainer_config(args.steps)
    dm = cfg.pipeline.datamanager
    dm.dataparser.downscale_factor = args.downscale_factor
    dm.num_initial_views, dm.initial_view_names = len(names), tuple(names)
    cfg.pipeline.selection.max_rounds = 0
    cfg.data, cfg.output_dir, cfg.timestamp, cfg.vis = args.scene, args.out / "runs", f"w{args.rank}", "tensorboard"
    cfg.steps_per_eval_all_images = cfg.steps_per_eval_image = cfg.steps_per_eval_batch = 10 * args.steps
    cfg.steps_per_save = 10 * args.steps
    first, last = args.window
    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    state: dict = {}
    original = HpgsTrainer.train_iteration

    def train_iteration(self, step):
        if args.rank == 0 and step == first:
            sync()
            state["prof"] = torch.profiler.profile(
                activities=[torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA])
            state["prof"].__enter__()
            state["t0"] = time.perf_counter()
        if args.rank == 0 and step == last and "prof" in state:
            sync()
            wall = time.perf_counter() - state["t0"]
            state["prof"].__exit__(None, None, None)
            summary = summarize(state.pop("prof"), last - first, wall)
            summary.update(concurrent=args.concurrent, mps=os.environ.get("CUDA_MPS_PIPE_DIRECTORY") is not None,
                           device=torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
                           gaussians=int(self.pipeline.model.num_points))
            (args.out / "profile.json").write_text(json.dumps(summary, indent=1))
            print(json.dumps(summary)[:2000], flush=True)
        return original(self, step)

    HpgsTrainer.train_iteration = train_iteration
    train_main(cfg)


def parent(args: argparse.Namespace) -> None:
    import contextlib

    from hpgs_lab import mps as cuda_mps

    args.out.mkdir(parents=True, exist_ok=True)
    gpu = os.environ.get("CUDA_VISIBLE_DEVICES", "0").split(",")[0]
    with cuda_mps.daemons_for([gpu]) if args.mps == "on" else contextlib.nullcontext({}) as daemons:
        env = {**os.environ, **(daemons[gpu].env() if daemons else {})}
        procs = []
        for rank in range(args.concurrent):
            cmd = [sys.executable, __file__, "--worker", "--rank", str(rank)] + [
                a for a in sys.argv[1:] if a != "--worker"]
            log = open(args.out / f"worker{rank}.log", "w")
            procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=REPO))
        codes = [p.wait() for p in procs]
    print(f"profile_step: workers ended {codes}; {args.out / 'profile.json'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--views-json", type=Path, required=True)
    ap.add_argument("--scene-name", required=True)
    ap.add_argument("--steps", type=int, default=6100)
    ap.add_argument("--window", type=int, nargs=2, default=[6000, 6050])
    ap.add_argument("--downscale-factor", type=int, default=2)
    ap.add_argument("--concurrent", type=int, default=1)
    ap.add_argument("--mps", choices=["on", "off"], default="off")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--worker", action="store_true")
    ap.add_argument("--rank", type=int, default=0)
    args = ap.parse_args()
    args.out = args.out.resolve()
    worker(args) if args.worker else parent(args)


if __name__ == "__main__":
    main()
