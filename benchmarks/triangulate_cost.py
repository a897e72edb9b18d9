"""What triangulating seed points from the active views costs per call (hpgs_ns.scenes.triangulate), on this CPU.

For 4, 8, 12 and 20 of juicebox's training views (images_2, 400x224, spread evenly over the capture):
- `one_call`: `triangulate_views` from scratch (a temporary workspace): seconds by stage, points;
- `round`: the same views when a `TriangulationWorkspace` already holds all but the last 4 (a round added 4):
  only those 4 are extracted and only pairs with one of them matched.

    OMP_NUM_THREADS=1 python benchmarks/triangulate_cost.py [--data ../shared/data/juicebox] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

import numpy as np

from hpgs_ns.atomic_write import write_json_atomic

REPO = Path(__file__).resolve().parent.parent


def row(info) -> dict:
    return {"seconds": info.seconds["total"], "points": info.num_points, "ok": info.ok, "new_views": info.new_views,
            "pairs_matched": info.pairs_matched, "stages": {k: v for k, v in info.seconds.items() if k != "total"},
            "mean_track_length": round(info.mean_track_length, 3), "mean_reprojection_error_px": round(info.mean_reprojection_error, 3)}


def round_after(cameras, paths, views, added: int):
    """The call after a round added the last `added` of `views` (a workspace holds the others)."""
    from hpgs_ns.scenes.triangulate import TriangulationWorkspace, triangulate_views

    with TriangulationWorkspace() as workspace:
        triangulate_views(cameras, paths, views[:-added], existing=workspace)
        return triangulate_views(cameras, paths, views, existing=workspace)[2]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("HPGS_SHARED", REPO.parent / "shared")) / "data" / "juicebox")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--views", type=int, nargs="+", default=[4, 8, 12, 20])
    ap.add_argument("--added", type=int, default=4, help="views a round adds, for the `round` cost")
    ap.add_argument("--repeats", type=int, default=2, help="each call is timed this many times; the fastest is kept")
    args = ap.parse_args()

    from hpgs_ns.dataparser import MipNerf360DataParserConfig
    from hpgs_ns.scenes.triangulate import DEFAULT_MAX_IMAGE_SIZE, DEFAULT_MIN_POINTS, triangulate_views

    outputs = MipNerf360DataParserConfig(data=args.data, downscale_factor=2).setup().get_dataparser_outputs("train")
    cameras, paths = outputs.cameras, outputs.image_filenames
    results = []
    for n in args.views:
        views = np.linspace(0, len(paths) - 1, n).round().astype(int).tolist()
        one = min((triangulate_views(cameras, paths, views)[2] for _ in range(args.repeats)), key=lambda i: i.seconds["total"])
        line = f"{n:3d} views: one call {one.seconds['total']:6.2f} s, {one.num_points:5d} points"
        later = None
        if n > args.added:
            later = min((round_after(cameras, paths, views, args.added) for _ in range(args.repeats)), key=lambda i: i.seconds["total"])
            line += f" | round adding {args.added}: {later.seconds['total']:6.2f} s, {later.num_points:5d} points"
        results.append({"views": n, "one_call": row(one), "round": row(later) if later else None})
        print(line, flush=True)

    payload = {
        "scene": args.data.name, "image_size": [int(cameras.width[0]), int(cameras.height[0])],
        "training_views": len(paths), "max_image_size": DEFAULT_MAX_IMAGE_SIZE, "min_points": DEFAULT_MIN_POINTS,
        "matching": "exhaustive (<= 30 views)",
        "machine": f"{platform.machine()} cpu x{os.cpu_count()}", "omp_threads": os.environ.get("OMP_NUM_THREADS"),
        "results": results,
        "repeats": args.repeats,
        "note": f"seconds: wall time of one call, the fastest of {args.repeats} (pycolmap uses every core); `round`: the call after a "
                f"round added {args.added} views, with a TriangulationWorkspace holding the earlier views' features and matches; "
                "ok false: fewer than min_points (the caller falls back to random points)",
    }
    path = write_json_atomic(args.out / "triangulate_cost.json", payload)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
