"""Where splatfacto's random start puts its points: the share inside the cameras' box and inside the scene's COLMAP
points (5-95% box per axis), both in nerfstudio's normalised frame, for `--pipeline.model.random-scale` values, and
the same for `--pipeline.datamanager.random-points views` drawn along the FisherRF protocol's 4 initial (farthest)
views; plus the share within 2% of the scene's extent of a COLMAP point ("near").

splatfacto samples `num_random` (50000) means uniformly in a cube of side `random-scale` (10) around the origin;
the dataparsers scale the cameras into [-1, 1]. Prints a table and writes JSON.

    python benchmarks/random_start_coverage.py [--scales 10 4 2] [--out benchmarks/results/random_start_coverage.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from hpgs_ns.atomic_write import write_json_atomic

SCENES = {  # name: (folder under ../shared/data, parser)
    "ethiopian-head": ("ethiopian-head", "mipnerf360"), "alexander": ("alexander", "mipnerf360"),
    "figurine-desk": ("figurine-desk", "mipnerf360"), "snowmiku-plush": ("snowmiku-plush", "mipnerf360"),
    "gerrard-hall": ("gerrard-hall", "mipnerf360"), "room-lab": ("room-lab", "mipnerf360"),
    "bonsai": ("mipnerf360-bonsai-device", "mipnerf360"), "juicebox": ("juicebox", "mipnerf360"),
    "fox": ("fox-nerfstudio", "nerfstudio-data"),
}


def outputs(folder: Path, parser: str):
    from hpgs_ns.dataparser import HpgsNerfstudioDataParserConfig, MipNerf360DataParserConfig

    if parser == "mipnerf360":
        config = MipNerf360DataParserConfig(data=folder, downscale_factor=2)
    else:
        config = HpgsNerfstudioDataParserConfig(data=folder, downscale_factor=2, eval_mode="interval", eval_interval=8)
    return config.setup().get_dataparser_outputs("train")


def views_points(out, count: int) -> np.ndarray:
    """`random-points views` along the FisherRF start's 4 farthest views (colours not needed here)."""
    import torch

    from hpgs_ns.scenes.view_points import points_along_views
    from hpgs_ns.selectors.farthest import farthest_point_order

    cameras = out.cameras
    views = sorted(farthest_point_order(cameras.camera_to_worlds[:, :3, 3], 4, start=0))
    blank = lambda view: np.zeros((int(cameras.height[view]), int(cameras.width[view]), 3), np.uint8)  # noqa: E731
    xyz, _ = points_along_views(cameras, blank, views, count, torch.Generator().manual_seed(0))
    return xyz.numpy()


def share_near(points: np.ndarray, colmap: np.ndarray, extent: float, fraction: float = 0.02) -> float:
    from sklearn.neighbors import NearestNeighbors

    distance = NearestNeighbors(n_neighbors=1).fit(colmap).kneighbors(points)[0][:, 0]
    return float((distance < fraction * extent).mean())


def share_inside(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    return float(np.all((points >= lo) & (points <= hi), axis=1).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-root", type=Path, default=Path("../shared/data"))
    parser.add_argument("--scales", type=float, nargs="+", default=[10.0, 4.0, 2.0])
    parser.add_argument("--num-random", type=int, default=50000)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/random_start_coverage.json"))
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    unit = rng.random((args.num_random, 3)) - 0.5  # splatfacto: (rand - 0.5) * random_scale
    rows = []
    for name, (folder, kind) in SCENES.items():
        path = args.data_root / folder
        if not path.is_dir():
            print(f"{name}: {path} not found, skipped")
            continue
        out = outputs(path, kind)
        centres = out.cameras.camera_to_worlds[:, :3, 3].numpy()
        row = {"scene": name, "cameras_box": [centres.min(0).tolist(), centres.max(0).tolist()], "scales": {}}
        xyz = out.metadata.get("points3D_xyz")
        if xyz is not None:
            xyz = xyz.numpy()
            row["points_box"] = [np.percentile(xyz, 5, 0).tolist(), np.percentile(xyz, 95, 0).tolist()]
        starts = {str(scale): unit * scale for scale in args.scales}
        starts["views"] = views_points(out, args.num_random)
        for name, random in starts.items():
            entry = {"in_cameras_box": share_inside(random, centres.min(0), centres.max(0))}
            if "points_box" in row:
                entry["in_points_box"] = share_inside(random, *map(np.array, row["points_box"]))
                extent = float(np.linalg.norm(np.percentile(xyz, 95, 0) - np.percentile(xyz, 5, 0)))
                entry["near_points"] = share_near(random, xyz, extent)
            row["scales"][name] = entry
        rows.append(row)
    names = [str(s) for s in args.scales] + ["views"]
    heads = [f"random-scale {float(n):g}" if n != "views" else "random-points views" for n in names]
    print("| scene | " + " | ".join(f"{h}: in cameras' box / in points' box / near a point" for h in heads) + " |")
    print("|---" * (len(names) + 1) + "|")
    for row in rows:
        cells = []
        for name in names:
            e = row["scales"][name]
            points = f"{100 * e['in_points_box']:.1f}%" if "in_points_box" in e else "-"
            near = f"{100 * e['near_points']:.1f}%" if "near_points" in e else "-"
            cells.append(f"{100 * e['in_cameras_box']:.1f}% / {points} / {near}")
        print(f"| {row['scene']} | " + " | ".join(cells) + " |")
    write_json_atomic(args.out, {"num_random": args.num_random, "rows": rows})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
