"""Fisher's exact shortcuts (`sh-via-color`, `drop-hidden`, `linearize`): seconds per round and pairs, on and off.

Scores every candidate of one round with each combination on the same probes and reports seconds, the pairs
differentiated (of those in the views' frusta), and how close the scores are to the plain computation
(max relative difference; the shortcuts are exact, so only float rounding should show). Prints a table and
writes JSON.

    python benchmarks/fisher_shortcuts.py --run outputs/scene/hpgs/<timestamp> --out fisher_shortcuts.json
    python benchmarks/fisher_shortcuts.py --synthetic occluded --steps 300 --out fisher_shortcuts.json   # CPU
"""

from __future__ import annotations

import argparse
import platform
import random
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from fisher_probes import load_run  # benchmarks/ is on sys.path when this script runs

SHORTCUTS = ("sh_via_color", "drop_hidden", "linearize")
# Plain first (the scores' reference), each shortcut alone, then the defaults (`linearize` implies `sh_via_color`).
COMBOS = [(False, False, False), (True, False, False), (False, True, False), (True, False, True), (True, True, True)]


def train_synthetic(layout: str, steps: int, folder: Path):
    """A short CPU run on an embedded procedural scene, 12 initial views, no rounds."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from conftest import run_training, short_config

    from hpgs_ns.scenes.synthetic import make_scene

    # Seeded as ns-train seeds with --machine.seed 0 (run_training alone does not).
    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)
    scene = make_scene(folder / layout, layout=layout, num_cameras=40, width=128, height=96, num_points=3000, seed=0)
    cfg = short_config(scene, folder / "run", steps=steps, rounds=0, initial=12)
    cfg.pipeline.model.sh_degree_interval = max(steps // 4, 1)  # reach SH degree 3 within the run
    trainer = run_training(cfg)
    return trainer.pipeline.datamanager, trainer.pipeline.model, steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--run", type=Path, help="run folder holding config.yml")
    src.add_argument("--synthetic", help="train this embedded layout (ring, occluded, sparse-objects) on the CPU")
    ap.add_argument("--steps", type=int, default=300, help="training steps for --synthetic")
    ap.add_argument("--probes", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True, help="JSON to write")
    args = ap.parse_args()

    from hpgs_ns.atomic_write import write_json_atomic
    from hpgs_ns.selection.config import SelectionConfig
    from hpgs_ns.selection.rounds import SelectionRounds
    from hpgs_ns.selectors.fisher import FisherSelectorConfig

    with tempfile.TemporaryDirectory() as tmp:
        dm, model, step = load_run(args.run) if args.run else train_synthetic(args.synthetic, args.steps, Path(tmp))
        cuda = torch.cuda.is_available()

        def one_round(combo, seed: int):
            ctx = SelectionRounds(SelectionConfig(), dm, model, selector=FisherSelectorConfig().setup()).context(step)
            ctx.generator, ctx.num_to_pick = torch.Generator().manual_seed(seed), 1
            cfg = FisherSelectorConfig(probes=args.probes, **dict(zip(SHORTCUTS, combo)))
            if cuda:
                torch.cuda.synchronize()
            start = time.perf_counter()
            selection = cfg.setup().select(ctx)
            if cuda:
                torch.cuda.synchronize()
            return time.perf_counter() - start, selection

        one_round(COMBOS[-1], 0)  # warm-up: kernels, allocator
        rows, plain = [], None
        for combo in COMBOS:
            runs = [one_round(combo, seed) for seed in range(args.repeats)]
            seconds = [r[0] for r in runs]
            selection = runs[0][1]
            if plain is None:
                plain = selection.scores
            rel = max(abs(selection.scores[c] - plain[c]) / max(abs(plain[c]), 1e-30) for c in plain)
            row = {
                **dict(zip(SHORTCUTS, combo)), "seconds_per_round": sum(seconds) / len(seconds),
                "pairs_differentiated": selection.work.get("pairs_differentiated"),
                "pairs_in_frustum": selection.work.get("pairs_in_frustum"),
                "max_relative_score_difference": rel, "pick": selection.indices,
            }
            rows.append(row)
            flags = " ".join(f"{n}={v!s:5}" for n, v in zip(SHORTCUTS, combo))
            print(f"{flags} {row['seconds_per_round']:8.2f} s/round  "
                  f"pairs {row['pairs_differentiated']:.0f} of {row['pairs_in_frustum']:.0f}  "
                  f"scores vs plain {rel:.1e}  pick {selection.indices}", flush=True)
        device = torch.cuda.get_device_name(0) if cuda else f"cpu ({platform.processor() or 'x86_64'})"
        write_json_atomic(args.out, {
            "source": str(args.run or f"synthetic:{args.synthetic}"), "step": step, "gaussians": int(model.num_points),
            "probes": args.probes, "candidates": len(dm.candidates), "active": len(dm.active), "device": device,
            "threads": torch.get_num_threads(), "rows": rows,
        })


if __name__ == "__main__":
    main()
