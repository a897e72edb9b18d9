"""Runs per GPU-hour against runs at once, with and without CUDA MPS: one `hpgs bench` batch per configuration.

A batch is N runs at once on one GPU (`--runs-per-gpu N`, `--mps on|off`, `CUDA_VISIBLE_DEVICES` pinned), all
started together: `farthest` on the given scenes, seeds spread so that the N runs are N (scene, seed) pairs (the
same pairs for the same N, so a batch with MPS pairs with one without). Each GPU runs its queue of batches one
after another, the GPUs side by side:

    python benchmarks/throughput.py run --gpus 0=off:8 1=off:4 2=on:8,on:4,on:1 3=on:16,on:12 \
        --suite real6 --suite-scenes juicebox stitch --data-root DIR --out /tmp/throughput
    python benchmarks/throughput.py rows /tmp/throughput --json benchmarks/results/throughput/h100.json \
        --plot docs/throughput.png

`rows` writes one row per batch (the issue's fields): device, mps (observed: every run was seen as an MPS
client), runs_at_once, steps, scenes, wall_s (the batch's `hpgs bench` from start to end, start-up included),
runs_per_gpu_hour (finished runs x 3600 / wall_s), median_step_ms (median over runs of each run's median step),
psnr_mean; plus the runs that failed. It prints the paired PSNR differences between batches of the same N with and
without MPS.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Tuple

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hpgs_ns.atomic_write import atomic_path  # noqa: E402


def parse_queue(text: str) -> Tuple[str, List[Tuple[str, int]]]:
    """`2=on:8,on:4` -> ("2", [("on", 8), ("on", 4)])."""
    gpu, _, batches = text.partition("=")
    return gpu, [(mode, int(n)) for mode, n in (b.split(":") for b in batches.split(","))]


def scene_seeds(scenes: List[str], n: int) -> Tuple[List[str], List[int]]:
    """N runs over the scenes: every scene x ceil(N / scenes) seeds, or the first N scenes at seed 0."""
    if n < len(scenes):
        return scenes[:n], [0]
    if n % len(scenes):
        raise SystemExit(f"throughput: {n} runs do not split evenly over {len(scenes)} scenes")
    return scenes, list(range(n // len(scenes)))


def batch_name(gpu: str, mode: str, n: int) -> str:
    return f"gpu{gpu}-mps{mode}-n{n}"


def run(args: argparse.Namespace) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    lock = threading.Lock()

    def queue(gpu: str, batches: List[Tuple[str, int]]) -> None:
        for mode, n in batches:
            scenes, seeds = scene_seeds(args.suite_scenes, n)
            name = batch_name(gpu, mode, n)
            cmd = [sys.executable, "-m", "hpgs_ns.cli", "bench", "--suite", args.suite, "--data-root", str(args.data_root),
                   "--suite-scenes", *scenes, "--protocols", args.protocol, "--selectors", args.selector,
                   "--seeds", *map(str, seeds), "--no-references", "--step-scale", str(args.step_scale),
                   "--runs-per-gpu", str(n), "--mps", mode, "--out", str(args.out / name)]
            env = {**os.environ, "CUDA_VISIBLE_DEVICES": gpu, "OMP_NUM_THREADS": str(args.threads)}
            start = time.time()
            with open(args.out / f"{name}.log", "w") as log:
                rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=REPO)
            record = {"name": name, "gpu": gpu, "mps": mode, "n": n, "scenes": scenes, "seeds": seeds,
                      "start": start, "end": time.time(), "rc": rc}
            with lock, open(args.out / "batches.jsonl", "a") as f:
                f.write(json.dumps(record) + "\n")
            print(json.dumps(record), flush=True)

    threads = [threading.Thread(target=queue, args=parse_queue(q)) for q in args.gpus]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def rows(args: argparse.Namespace) -> None:
    from hpgs_lab.report import load_results
    from hpgs_lab.report.tables import short_device

    batches = [json.loads(line) for line in (args.folder / "batches.jsonl").read_text().splitlines() if line.strip()]
    table, psnr = [], {}
    for b in batches:
        results = load_results(args.folder / b["name"]) if (args.folder / b["name"]).is_dir() else []
        wall = b["end"] - b["start"]
        steps = [r.steps for r in results]
        med = [r.timing.train_iter_ms_median for r in results if r.timing.train_iter_ms_median]
        row = {
            "device": short_device(results[0]) if results else "?",
            "mps": bool(results) and all(r.timing.mps is True for r in results),
            "mps_requested": b["mps"],
            "runs_at_once": b["n"],
            "steps": max(steps) if steps else None,
            "scenes": b["scenes"],
            "wall_s": round(wall, 1),
            "runs_per_gpu_hour": round(len(results) * 3600 / wall, 1),
            "median_step_ms": round(statistics.median(med), 2) if med else None,
            "psnr_mean": round(statistics.fmean(r.test.psnr for r in results), 3) if results else None,
            "runs_finished": len(results),
            "runs_failed": b["n"] - len(results),
        }
        table.append(row)
        psnr[(b["mps"], b["n"])] = {(r.scene, r.seed): r.test.psnr for r in results}
        print(json.dumps(row))
    for (mode, n), values in sorted(psnr.items()):
        other = psnr.get(("off", n)) if mode == "on" else None
        if other:
            keys = sorted(set(values) & set(other))
            diffs = [values[k] - other[k] for k in keys]
            if len(diffs) > 1:
                sd = statistics.stdev(diffs)
                half = 1.96 * sd / math.sqrt(len(diffs))
                print(f"N={n}: MPS - no MPS, {len(diffs)} pairs: {statistics.fmean(diffs):+.3f} dB "
                      f"[{statistics.fmean(diffs) - half:+.3f}, {statistics.fmean(diffs) + half:+.3f}], SD {sd:.3f}")
    # Every (scene, seed) run both ways: the mean of its MPS runs (any N) minus the mean of its runs without MPS.
    cells: Dict[Tuple[str, int], Dict[str, List[float]]] = {}
    for (mode, _n), values in psnr.items():
        for key, value in values.items():
            cells.setdefault(key, {}).setdefault(mode, []).append(value)
    diffs = [statistics.fmean(c["on"]) - statistics.fmean(c["off"]) for c in cells.values() if "on" in c and "off" in c]
    if len(diffs) > 1:
        mean, half = statistics.fmean(diffs), 1.96 * statistics.stdev(diffs) / math.sqrt(len(diffs))
        print(f"every N: MPS - no MPS, {len(diffs)} (scene, seed) cells: {mean:+.3f} dB [{mean - half:+.3f}, {mean + half:+.3f}]")
    for mode in ("off", "on"):  # the spread of repeats of one (scene, seed), pooled
        groups = [c[mode] for c in cells.values() if len(c.get(mode, [])) > 1]
        dof = sum(len(g) - 1 for g in groups)
        if dof:
            ss = sum((v - statistics.fmean(g)) ** 2 for g in groups for v in g)
            print(f"repeat SD {'with' if mode == 'on' else 'without'} MPS: {math.sqrt(ss / dof):.3f} dB ({dof} df)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(args.json) as tmp:
            Path(tmp).write_text(json.dumps(table, indent=1) + "\n")
    if args.plot:
        plot(table, args.plot, args.baseline)


def plot(table: List[Dict], path: Path, baseline: List[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for mps, style in ((True, "o-"), (False, "s--")):
        points = sorted((r["runs_at_once"], r["runs_per_gpu_hour"]) for r in table if r["mps"] == mps and not r["runs_failed"])
        if points:
            ax.plot(*zip(*points), style, label=f"{'with' if mps else 'without'} MPS ({table[0]['device']}, this run)")
    if baseline:  # earlier measurements without MPS, N:runs-per-hour
        pts = sorted((int(n), float(v)) for n, v in (b.split(":") for b in baseline))
        ax.plot(*zip(*pts), "x:", color="gray", label="without MPS (docs' earlier curve, H100)")
    ax.set_xlabel("runs at once on one GPU")
    ax.set_ylabel("runs per GPU-hour")
    ax.set_title(f"FisherRF protocol, 20000 steps, {' + '.join(max((r['scenes'] for r in table), key=len))}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format=path.suffix.lstrip("."))
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--gpus", nargs="+", required=True, help="GPU=MODE:N,MODE:N ... (MODE on|off)")
    r.add_argument("--suite", default="real6")
    r.add_argument("--suite-scenes", nargs="+", required=True)
    r.add_argument("--data-root", type=Path, default=Path("../shared/data"))
    r.add_argument("--protocol", default="fisherrf")
    r.add_argument("--selector", default="farthest")
    r.add_argument("--step-scale", type=float, default=1.0)
    r.add_argument("--threads", type=int, default=2, help="OMP_NUM_THREADS of every run")
    r.add_argument("--out", type=Path, required=True)
    s = sub.add_parser("rows")
    s.add_argument("folder", type=Path)
    s.add_argument("--json", type=Path)
    s.add_argument("--plot", type=Path)
    s.add_argument("--baseline", nargs="*", default=[], help="N:RUNS_PER_HOUR of an earlier curve to draw")
    args = ap.parse_args()
    run(args) if args.cmd == "run" else rows(args)


if __name__ == "__main__":
    main()
