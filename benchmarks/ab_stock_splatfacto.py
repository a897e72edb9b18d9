"""A/B: training speed of an `hpgs` run without rounds against stock `ns-train splatfacto`, same views, same steps, GPU.

`hpgs`: the project's trainer, datamanager and model on the given views from step 0 with no selection rounds (what
`hpgs bench --final-set` trains). `stock`: nerfstudio's own `splatfacto` method config (its Trainer,
FullImageDatamanager and SplatfactoModel), its dataparser the project's `mipnerf360` parser keeping only those
training views (the test views stay as they are). Stock splatfacto downloads AlexNet for LPIPS at start-up; this
harness (only) swaps in the offline LPIPS so it can start offline.

    python benchmarks/ab_stock_splatfacto.py --scene PATH --variant {hpgs,stock} --out DIR [--steps 20000] \
        [--views-json benchmarks/results/judge-full/farthest_views.json --scene-name stitch | --views 27]
prints and writes DIR/<variant>.json with ms/iteration (median of nerfstudio's logged running means and
train_total / steps), wall time, test PSNR where evaluated, and the Gaussian count.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import torch


def subset_parser(views):
    """The project's mipnerf360 parser keeping only `views` (file names) of the training split."""
    import dataclasses

    from hpgs_ns.dataparser import MipNerf360DataParser, MipNerf360DataParserConfig

    names = {Path(v).name for v in views}  # recorded as "images/0001.jpg"; the parser lists images_2/0001.jpg

    class SubsetParser(MipNerf360DataParser):
        def _generate_dataparser_outputs(self, split: str = "train", **kwargs):
            out = super()._generate_dataparser_outputs(split, **kwargs)
            if split != "train":
                return out
            keep = [i for i, f in enumerate(out.image_filenames) if f.name in names]
            if len(keep) != len(names):
                raise SystemExit(f"ab_stock_splatfacto: {len(names) - len(keep)} of the views are not training views")
            masks = out.mask_filenames and [out.mask_filenames[i] for i in keep]
            return dataclasses.replace(out, image_filenames=[out.image_filenames[i] for i in keep],
                                       cameras=out.cameras[torch.tensor(keep)], mask_filenames=masks)

    @dataclasses.dataclass
    class SubsetParserConfig(MipNerf360DataParserConfig):
        _target: type = dataclasses.field(default_factory=lambda: SubsetParser)

    return SubsetParserConfig


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--variant", choices=["hpgs", "stock"], required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=15000)
    ap.add_argument("--views", type=int, default=27, help="evenly spaced views (without --views-json)")
    ap.add_argument("--views-json", type=Path, help="a JSON {'views': {scene: [names]}} (e.g. farthest_views.json)")
    ap.add_argument("--scene-name", help="the scene's key in --views-json (default: the folder's name)")
    ap.add_argument("--downscale-factor", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from nerfstudio.scripts.train import main as train_main

    from hpgs_lab.runs import train_timing
    from hpgs_ns.method_config import hpgs_trainer_config
    from hpgs_ns.model import _offline_lpips_in_splatfacto

    names = None
    if args.views_json:
        names = sorted(json.loads(args.views_json.read_text())["views"][args.scene_name or args.scene.name])
    if args.variant == "stock":
        from nerfstudio.configs.method_configs import method_configs

        cfg = copy.deepcopy(method_configs["splatfacto"])
        if names is None:
            raise SystemExit("ab_stock_splatfacto: --variant stock needs --views-json (the views to keep)")
        cfg.max_num_iterations = args.steps
        for group in cfg.optimizers.values():  # schedules sized to the run, as hpgs sizes its own
            if group.get("scheduler") is not None and hasattr(group["scheduler"], "max_steps"):
                group["scheduler"].max_steps = args.steps
        cfg.pipeline.datamanager.dataparser = subset_parser(names)(downscale_factor=args.downscale_factor)
        cfg.machine.seed = args.seed
    else:
        cfg = hpgs_trainer_config(args.steps)
        dm = cfg.pipeline.datamanager
        dm.dataparser.downscale_factor = args.downscale_factor
        dm.seed, cfg.machine.seed = args.seed, args.seed
        if names is not None:
            dm.num_initial_views, dm.initial_view_names = len(names), tuple(names)
        else:
            dm.num_initial_views = args.views
        cfg.pipeline.selection.max_rounds = 0
    cfg.data = args.scene
    cfg.output_dir = args.out / "runs"
    cfg.timestamp = args.variant
    cfg.vis = "tensorboard"
    cfg.steps_per_eval_all_images = 10 * args.steps
    cfg.steps_per_eval_image = 10 * args.steps
    cfg.steps_per_eval_batch = 10 * args.steps
    cfg.steps_per_save = args.steps
    start = time.perf_counter()
    with _offline_lpips_in_splatfacto():
        train_main(cfg)
    wall = time.perf_counter() - start
    run_dir = next((args.out / "runs").rglob(f"{args.variant}/config.yml")).parent
    timing = train_timing(run_dir)
    # weights_only=False: its own file, and stock checkpoints hold more than tensors
    ckpt = torch.load(next((run_dir / "nerfstudio_models").glob("*.ckpt")), map_location="cpu", weights_only=False)
    n_gauss = int(ckpt["pipeline"]["_model.gauss_params.means"].shape[0])
    result = {
        "variant": args.variant,
        "steps": args.steps,
        "views": len(names) if names else args.views,
        "scene": str(args.scene),
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
