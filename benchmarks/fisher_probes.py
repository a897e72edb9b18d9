"""Fisher's probe count K: run time against error, on a trained `hpgs` run.

Loads the run's last checkpoint (its active set comes with it), scores every candidate with K probes for each K
in `--probes`, and compares each ranking with a reference K (`--reference`, default 256): Spearman rank
correlation, whether the top pick agrees, and seconds per round. Prints a table and writes JSON.

    python benchmarks/fisher_probes.py --run outputs/scene/hpgs/<timestamp> --out fisher_probes.json
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path
from typing import Dict, List

import torch


def spearman(a: List[float], b: List[float]) -> float:
    ra = torch.tensor(a).argsort().argsort().double()
    rb = torch.tensor(b).argsort().argsort().double()
    ra, rb = ra - ra.mean(), rb - rb.mean()
    return float((ra * rb).sum() / (ra.norm() * rb.norm()))


def load_run(run: Path):
    """(datamanager, model, step) of a run's last checkpoint, set up as a selection round at that step sees it."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, step = eval_setup(run / "config.yml", test_mode="test")
    # splatfacto's load_state_dict sets step 30000 (full SH degree); a round at this step renders with the SH
    # degree of the step instead (up to 2026-11 this script scored degree 3 where the run's round used 1).
    pipeline.model.step = step
    return pipeline.datamanager, pipeline.model, step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="run folder holding config.yml")
    ap.add_argument("--out", type=Path, required=True, help="JSON to write")
    ap.add_argument("--probes", type=int, nargs="+", default=[4, 8, 16, 32, 64])
    ap.add_argument("--reference", type=int, default=256)
    ap.add_argument("--view-batch", type=int, nargs="+", default=None,
                    help="views per batched render, each timed (default: the selector's default)")
    ap.add_argument("--resolution-scale", type=float, nargs="+", default=None,
                    help="render scales to time and rank against the reference (default: the selector's default)")
    ap.add_argument("--train-probe-factor", type=int, nargs="+", default=None,
                    help="H_train probe factors to time and rank (default: the selector's default)")
    ap.add_argument("--reference-scale", type=float, default=None,
                    help="render scale of the reference ranking (default: the selector's default)")
    ap.add_argument("--profile", type=Path, default=None,
                    help="also profile one round at the default K with torch.profiler and write its op table here")
    ap.add_argument("--repeats", type=int, default=3, help="seeds per K (the spread of the estimate)")
    args = ap.parse_args()

    from hpgs_ns.atomic_write import write_json_atomic
    from hpgs_ns.selection.config import SelectionConfig
    from hpgs_ns.selection.rounds import SelectionRounds
    from hpgs_ns.selectors.fisher import FisherSelectorConfig

    dm, model, step = load_run(args.run)

    default = FisherSelectorConfig()
    view_batches = args.view_batch or [default.view_batch]
    res_scales = args.resolution_scale or [default.resolution_scale]
    factors = args.train_probe_factor or [default.train_probe_factor]
    ref_scale = args.reference_scale or default.resolution_scale

    def scores(k: int, seed: int, view_batch: int = view_batches[0], scale: float = default.resolution_scale,
               factor: int = default.train_probe_factor) -> Dict[int, float]:
        ctx = SelectionRounds(SelectionConfig(), dm, model, selector=FisherSelectorConfig().setup()).context(step)
        ctx.generator = torch.Generator().manual_seed(seed)
        ctx.num_to_pick = 1
        config = FisherSelectorConfig(probes=k, view_batch=view_batch, resolution_scale=scale, train_probe_factor=factor)
        return config.setup().select(ctx).scores

    t = time.perf_counter()
    scores(4, 0)  # warm-up (CUDA kernels, allocator)
    first_call = time.perf_counter() - t
    print(f"first call (K=4, one-off set-up included): {first_call:.2f} s", flush=True)
    if args.profile is not None:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.cuda.is_available() else [])
        with profile(activities=acts) as prof:
            scores(FisherSelectorConfig().probes, 0)
            if torch.cuda.is_available():
                torch.cuda.synchronize()
        sort = "self_cuda_time_total" if torch.cuda.is_available() else "self_cpu_time_total"
        averages = prof.key_averages()
        # The named ranges of pair_render and the fisher selector: where a round's time goes, stage by stage.
        stages = [e for e in averages if e.key.startswith(("pair_render.", "fisher."))]
        lines = [f"{e.key:28s} calls {e.count:5d}  CPU total {e.cpu_time_total / 1e3:9.1f} ms  "
                 f"device total {getattr(e, 'device_time_total', getattr(e, 'cuda_time_total', 0)) / 1e3:9.1f} ms"
                 for e in sorted(stages, key=lambda e: e.key)]
        table = "\n".join(lines) + "\n\n" + averages.table(sort_by=sort, row_limit=40)
        args.profile.write_text(table)
        print(table, flush=True)
    ref = scores(args.reference, 12345, scale=ref_scale)
    order = sorted(ref)
    ref_list = [ref[c] for c in order]
    best = max(ref, key=ref.get)
    rows = []
    grid = [(vb, k, sc, f) for vb in view_batches for k in args.probes for sc in res_scales for f in factors]
    for vb, k, sc, f in grid:
        rhos, tops, secs = [], [], []
        for seed in range(args.repeats):
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            t = time.perf_counter()
            s = scores(k, seed, vb, sc, f)
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            secs.append(time.perf_counter() - t)
            rhos.append(spearman([s[c] for c in order], ref_list))
            tops.append(max(s, key=s.get) == best)
        row = {"probes": k, "view_batch": vb, "resolution_scale": sc, "train_probe_factor": f,
               "seconds_per_round": sum(secs) / len(secs), "spearman_vs_reference": sum(rhos) / len(rhos),
               "spearman_min": min(rhos), "top_pick_agrees": sum(tops) / len(tops)}
        rows.append(row)
        print(f"K={k:4d} view_batch={vb:4d} scale={sc:.2f} train_factor={f}  {row['seconds_per_round']:7.2f} s/round  "
              f"Spearman {row['spearman_vs_reference']:.3f} "
              f"(min {row['spearman_min']:.3f})  top pick agrees {100 * row['top_pick_agrees']:.0f}%", flush=True)
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else f"cpu ({platform.processor() or 'x86_64'})"
    write_json_atomic(args.out, {
        "run": str(args.run), "step": step, "gaussians": int(model.num_points), "candidates": len(ref),
        "active": len(dm.active), "reference_probes": args.reference,
        "reference_scale": ref_scale, "first_call_seconds": first_call, "device": device, "rows": rows,
    })


if __name__ == "__main__":
    main()
