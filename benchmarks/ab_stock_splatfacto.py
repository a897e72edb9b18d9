"""A/B: training speed of hpgs's model against stock nerfstudio splatfacto, same views, same steps, same GPU.

Both variants use the active datamanager with `num-initial-views` evenly spaced views and no selection rounds,
so the only difference is the model class (`HpgsSplatfactoModel` vs `SplatfactoModel`). Stock splatfacto
downloads AlexNet for LPIPS at start-up; this harness (only) swaps in the offline LPIPS so it can start offline.

    python benchmarks/ab_stock_splatfacto.py --scene PATH --variant {hpgs,stock} --out DIR [--steps 15000]
prints and writes DIR/<variant>.json with ms/iteration (median of nerfstudio's logged running means and
train_total / steps), test PSNR and the Gaussian count.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--variant", choices=["hpgs", "stock"], required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=15000)
    ap.add_argument("--views", type=int, default=27)
    ap.add_argument("--downscale-factor", type=int, default=2)
    args = ap.parse_args()

    from nerfstudio.models.splatfacto import SplatfactoModelConfig
    from nerfstudio.scripts.train import main as train_main

    from hpgs_ns.bench.runs import train_timing
    from hpgs_ns.method_config import hpgs_trainer_config
    from hpgs_ns.model import _offline_lpips_in_splatfacto

    cfg = hpgs_trainer_config(args.steps)
    cfg.data = args.scene
    cfg.output_dir = args.out / "runs"
    cfg.timestamp = args.variant
    cfg.vis = "tensorboard"
    cfg.steps_per_eval_all_images = 10 * args.steps
    cfg.steps_per_eval_image = 10 * args.steps
    cfg.steps_per_save = args.steps
    dm = cfg.pipeline.datamanager
    dm.num_initial_views, dm.max_rounds = args.views, 0
    dm.dataparser.downscale_factor = args.downscale_factor
    if args.variant == "stock":
        cfg.pipeline.model = SplatfactoModelConfig()
    start = time.perf_counter()
    with _offline_lpips_in_splatfacto():
        train_main(cfg)
    wall = time.perf_counter() - start
    run_dir = next((args.out / "runs").rglob(f"{args.variant}/config.yml")).parent
    timing = train_timing(run_dir)
    ckpt = torch.load(next((run_dir / "nerfstudio_models").glob("*.ckpt")), map_location="cpu", weights_only=True)
    n_gauss = int(ckpt["pipeline"]["_model.gauss_params.means"].shape[0])
    result = {
        "variant": args.variant,
        "steps": args.steps,
        "views": args.views,
        "wall_seconds": wall,
        "train_iter_ms_median": timing.get("train_iter_ms_median"),
        "train_ms_per_step_total": 1000 * timing["train_total_seconds"] / args.steps if timing.get("train_total_seconds") else None,
        "gaussians_final": n_gauss,
        "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
    }
    print(json.dumps(result))
    (args.out / f"{args.variant}.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
