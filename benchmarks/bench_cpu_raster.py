"""Benchmark of hpgs_ns.cpu_raster.rasterization on the CPU: time and peak memory against N and image size.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_cpu_raster.py [--threads 1 2]
        [--out benchmarks/results/cpu_raster.json]

For every (threads, N in {1k, 10k, 100k}, image side in {32, 64, 128, 256}) a fresh Python process builds a random
scene, renders it splatfacto-style (SH degree 3, packed=False, RGB+ED, absgrad=True) and back-propagates an L2 loss:
- forward and forward+backward wall time: median of several runs after one warm-up run;
- peak memory: the rise of the process's peak resident set size (getrusage ru_maxrss) during the first forward,
  and during the first forward+backward, over the resident size just before it (fresh process per configuration,
  so the peak belongs to that configuration alone; it includes allocator slack and the autograd graph);
- the work: valid (camera, Gaussian) pairs, tile intersections, coverage (mean alpha).
The scene: Gaussians in a box in front of a 0.9 x width focal-length camera (z in ~[3, 5]), random rotations,
log-normal scales with a median of 0.03 x (10k / N)^(1/3) (more Gaussians, smaller ones, as in a real scene), so
the image is mostly covered at every N. Also written: the machine (CPU model, load average before and after the
sweep, torch version and threads), since timings on a shared machine are noisy.
The JSON is written to a temporary file and renamed, so a killed run never leaves a truncated result.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SIZES = (32, 64, 128, 256)
COUNTS = (1_000, 10_000, 100_000)


def _rss_kib() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * (os.sysconf("SC_PAGE_SIZE") // 1024)


def run_one(n: int, size: int, threads: int, repeats: int) -> dict:
    """One configuration, in this (fresh) process."""
    import torch

    from hpgs_ns.cpu_raster import rasterization

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * torch.tensor([1.0, 1.0, 0.5]) + torch.tensor([0.0, 0.0, 4.0])
    scale = 0.03 * (10_000 / n) ** (1 / 3)
    params = dict(
        means=means,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.exp(torch.randn(n, 3, generator=g) * 0.4) * scale,
        opacities=torch.sigmoid(torch.randn(n, generator=g) * 1.5),
        colors=torch.randn(n, 16, 3, generator=g) * 0.3,
    )
    for v in params.values():
        v.requires_grad_()
    f = 0.9 * size
    cam = dict(viewmats=torch.eye(4)[None], Ks=torch.tensor([[[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]]]),
               width=size, height=size)
    target = torch.rand(1, size, size, 3, generator=g)
    kw = dict(sh_degree=3, packed=False, render_mode="RGB+ED", absgrad=True, near_plane=0.01, far_plane=1e10)

    def forward():
        return rasterization(**params, **cam, **kw)

    def backward(out):
        render, alphas, meta = out
        meta["means2d"].retain_grad()
        (((render[..., :3] - target) ** 2).sum() + alphas.sum()).backward()
        for v in params.values():
            v.grad = None

    # first run: peak memory of the forward, then of forward + backward
    rss0 = _rss_kib()
    out = forward()
    peak_fwd = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0
    backward(out)
    peak_fb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0
    meta = out[2]
    work = dict(valid_pairs=int((meta["radii"] > 0).sum()), intersections=int(meta["isect_ids"].shape[0]),
                coverage=float(out[1].mean()))
    del out

    fwd, fb = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = forward()
        t1 = time.perf_counter()
        backward(out)
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        fb.append(t2 - t0)
        del out
    return dict(n=n, size=size, threads=threads, forward_s=statistics.median(fwd), fwd_bwd_s=statistics.median(fb),
                forward_min_s=min(fwd), fwd_bwd_min_s=min(fb), repeats=repeats,
                peak_mem_forward_mib=max(peak_fwd, 0) / 1024, peak_mem_fwd_bwd_mib=max(peak_fb, 0) / 1024, **work)


def machine() -> dict:
    import torch

    model = ""
    try:
        model = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return dict(cpu=model or platform.processor(), cores=os.cpu_count(), torch=torch.__version__,
                python=platform.python_version(), load_average_before=os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "cpu_raster.json")
    ap.add_argument("--one", type=int, nargs=3, metavar=("N", "SIZE", "THREADS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one, repeats=args.repeats)))
        return

    from rich.console import Console
    from rich.table import Table

    console = Console(width=max(140, Console().width))
    info = machine()
    rows = []
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")]))
    for threads in args.threads:
        for n in args.counts:
            for size in args.sizes:
                repeats = args.repeats if n * size < 100_000 * 128 else max(2, args.repeats // 2)
                cmd = [sys.executable, __file__, "--one", str(n), str(size), str(threads), "--repeats", str(repeats)]
                res = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
                if res.returncode != 0:
                    console.print(f"[red]N={n} {size}^2 threads={threads} failed[/red]\n{res.stderr[-2000:]}")
                    continue
                row = json.loads(res.stdout.strip().splitlines()[-1])
                row["load_average_1min"] = os.getloadavg()[0]
                rows.append(row)
                console.print(f"threads={threads} N={n:>6} {size:>3}^2: fwd {row['forward_s']:.3f} s, "
                              f"fwd+bwd {row['fwd_bwd_s']:.3f} s, peak {row['peak_mem_fwd_bwd_mib']:.0f} MiB "
                              f"(load {row['load_average_1min']:.1f})")
    info["load_average_after"] = os.getloadavg()

    table = Table(title="hpgs_ns.cpu_raster: SH3, packed=False, RGB+ED, absgrad (median times)")
    for col in ("threads", "N", "image", "pairs", "isects", "cover", "fwd s", "fwd+bwd s", "peak fwd MiB",
                "peak fwd+bwd MiB", "load"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(str(r["threads"]), f"{r['n']:,}", f"{r['size']}^2", f"{r['valid_pairs']:,}",
                      f"{r['intersections']:,}", f"{r['coverage']:.2f}", f"{r['forward_s']:.3f}",
                      f"{r['fwd_bwd_s']:.3f}", f"{r['peak_mem_forward_mib']:.0f}", f"{r['peak_mem_fwd_bwd_mib']:.0f}",
                      f"{r['load_average_1min']:.1f}")
    console.print(table)

    result = dict(
        description=("hpgs_ns.cpu_raster.rasterization, splatfacto settings (SH degree 3, packed=False, RGB+ED, "
                     "absgrad=True), L2 loss backward; times are medians of repeated runs after a warm-up; "
                     "peak memory is the rise of ru_maxrss over the RSS before the first run, fresh process per row"),
        command=" ".join([Path(sys.executable).name, *sys.argv]),
        date=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        machine=info,
        rows=rows,
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=args.out.parent, prefix=".cpu_raster.", suffix=".json")
    with os.fdopen(fd, "w") as fh:
        json.dump(result, fh, indent=2)
    os.chmod(tmp, 0o644)
    os.replace(tmp, args.out)
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
