"""Projection + SH colour, forward and backward, over many (view, Gaussian) pairs: tiny-matrix `@` against the
broadcast outer products that `cpu_raster._mm` uses on CUDA. Prints seconds and writes JSON.

    python benchmarks/project_speed.py --pairs 1200000 --out project_speed.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from hpgs_ns import cpu_raster


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=1_200_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    g = torch.Generator(device="cpu").manual_seed(0)
    P = args.pairs
    means = torch.randn(P, 3, generator=g).to(dev).requires_grad_()
    quats = torch.randn(P, 4, generator=g).to(dev).requires_grad_()
    scales = (torch.rand(P, 3, generator=g) * 0.1).to(dev).requires_grad_()
    coeffs = torch.randn(P, 16, 3, generator=g).to(dev).requires_grad_()
    vm = torch.eye(4, device=dev).repeat(P, 1, 1)
    vm[:, 2, 3] = 5.0
    K = torch.tensor([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]], device=dev).repeat(P, 1, 1)

    def step() -> float:
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        cov = cpu_raster.quat_scale_to_covar(quats, scales)
        out = cpu_raster.project(means, cov, vm, K, 128, 96, 0.3, False)
        col = cpu_raster.sh_to_color(3, means, coeffs)
        (out["means2d"].sum() + out["conics"].sum() + col.sum()).backward()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - t

    rows = {}
    for name, broadcast in [("matmul", False), ("broadcast", True)]:
        cpu_raster._mm = (lambda a, b: cpu_raster._mm_broadcast(a, b)) if broadcast else (lambda a, b: a @ b)
        step()  # warm-up
        rows[name] = min(step() for _ in range(args.repeats))
        print(f"{name:10s} {rows[name] * 1e3:8.1f} ms  ({P} pairs, {dev})", flush=True)
    args.out.write_text(json.dumps({"pairs": P, "device": torch.cuda.get_device_name(0) if dev.type == "cuda" else "cpu",
                                    "seconds": rows}, indent=2))


if __name__ == "__main__":
    main()
