"""How many seed points triangulation from the active views yields, how accurate they are, and what a call costs,
for several feature/matching/verification settings (hpgs_ns.scenes.triangulate.TriangulationSettings, and the
rejected variants of benchmarks/triangulation_variants.py: guided matching, upsampled photos), on this CPU.

Each scene is read as the benchmark suites read it (tune6.toml, real6.toml: the suite's dataparser and options
over ../shared/data/<path>). Its views are taken in the order a FisherRF run adds them: the 4 farthest-point
initial views, then the `farthest` selector's picks, read from a committed run's JSON (`initial_views` +
`chosen_views`) or, for a scene without one, computed with the project's own code (datamanager's fps initial
views, FarthestSelector). The first 4, 8 and 16 views are triangulated from scratch (one call, a temporary
workspace) and each call records:
- points: how many were triangulated (below min_points 100 the run falls back to random points);
- median_distance: the median distance of the points to the nearest point of the scene's own COLMAP model (built
  from every photo), both in nerfstudio's normalised frame, as a fraction of the scene extent (the diagonal of the
  5th-95th percentile box of the COLMAP points, as tests/test_triangulate.py); fox has no COLMAP model: counts only;
- seconds: wall time of the call (pycolmap uses every core), and by stage.

Settings are chosen on the tuning scenes (tune6) and judged on real6 (CHOSEN: the setting chosen, now the
default). Results are merged into the JSON (a rerun of some scenes or variants keeps the others).

    OMP_NUM_THREADS=1 python benchmarks/triangulation_yield.py [--scenes bonsai fox] [--variants colmap poses]
        [--views 4 8 16] [--data-root ../shared/data] [--out benchmarks/results]
    python benchmarks/triangulation_yield.py --table --variants colmap poses-5-r9   # the JSON as a markdown table
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
from pathlib import Path
from types import SimpleNamespace
from typing import Dict, List, Optional

import numpy as np

from hpgs_ns.atomic_write import write_json_atomic

REPO = Path(__file__).resolve().parent.parent
TUNING = ["ethiopian-head", "alexander", "figurine-desk", "snowmiku-plush", "gerrard-hall", "room-lab"]
JUDGING = ["bonsai", "juicebox", "stitch", "mold-gold-cape", "campus-building", "fox"]
RUNS = {"real6": REPO / "benchmarks" / "results" / "suite", "tune6": REPO / "benchmarks" / "results" / "schedule-pilot"}

# name -> VariantSettings fields (the rest at COLMAP's defaults); guided* and *-up* run only here (triangulation_variants.py)
VARIANTS: Dict[str, dict] = {
    "colmap": {},  # (a) today's: COLMAP's SIFT, matcher and RANSAC verification
    "sift-low": {"peak_threshold": 0.002},  # (b) weaker SIFT peaks kept
    "sift-up": {"upscale_to": 800},  # (b) photos upsampled to 800 px long side before SIFT
    "sift-up-low": {"upscale_to": 800, "peak_threshold": 0.002},
    "inliers-5": {"min_num_inliers": 5},  # (d) RANSAC, lower minimum
    "poses": {"verification": "poses"},  # (c) matches kept by their epipolar distance under the known poses
    "poses-5": {"verification": "poses", "min_num_inliers": 5},  # (c + d)
    "poses-5-r9": {"verification": "poses", "min_num_inliers": 5, "max_ratio": 0.9},  # (c + d) + a looser ratio test
    "poses-3-r9": {"verification": "poses", "min_num_inliers": 3, "max_ratio": 0.9},
    "poses-5-r95": {"verification": "poses", "min_num_inliers": 5, "max_ratio": 0.95},
    "poses-5-r9-e2": {"verification": "poses", "min_num_inliers": 5, "max_ratio": 0.9, "max_epipolar_error": 2.0},
    "poses-5-r9-low": {"verification": "poses", "min_num_inliers": 5, "max_ratio": 0.9, "peak_threshold": 0.004},
    "poses-5-low": {"verification": "poses", "min_num_inliers": 5, "peak_threshold": 0.002},  # (b + c + d)
    "poses-5-up": {"verification": "poses", "min_num_inliers": 5, "upscale_to": 800},  # (b + c + d)
    "poses-5-up-low": {"verification": "poses", "min_num_inliers": 5, "upscale_to": 800, "peak_threshold": 0.002},
    # (c') the known poses guide the matching itself: each feature's ratio test among the other view's features near
    # its epipolar line only
    "guided": {"verification": "guided"},
    "guided-5": {"verification": "guided", "min_num_inliers": 5},
    "guided-5-e2": {"verification": "guided", "min_num_inliers": 5, "max_epipolar_error": 2.0},
    "guided-r7": {"verification": "guided", "max_ratio": 0.7},
    "guided-5-r7": {"verification": "guided", "min_num_inliers": 5, "max_ratio": 0.7},
    "guided-5-low": {"verification": "guided", "min_num_inliers": 5, "peak_threshold": 0.002},
    "guided-5-e2-low": {"verification": "guided", "min_num_inliers": 5, "max_epipolar_error": 2.0, "peak_threshold": 0.002},
}


CHOSEN = "poses-5-r9"  # by the tuning scenes at 4 and 8 views; hpgs_ns.scenes.triangulate.DEFAULT_SETTINGS


def load_scene(name: str, data_root: Path):
    """(suite, dataparser outputs of the training split) as the benchmark suite reads the scene."""
    from hpgs_lab.suites import load_suite
    from hpgs_ns.dataparser import DATAPARSERS

    suite = "tune6" if name in TUNING else "real6"
    scene = load_suite(suite, data_root, only=[name])[0]
    options = {k.replace("-", "_"): int(v) if v.isdigit() else v for k, v in scene.option_dict().items()}
    config = dataclasses.replace(DATAPARSERS[scene.dataparser], data=scene.path, **options)
    return suite, scene, config.setup().get_dataparser_outputs("train")


def committed_order(name: str, suite: str) -> Optional[dict]:
    """`initial_views` + `chosen_views` of a committed FisherRF/farthest run of `name` (16 picks), or None."""
    root = RUNS[suite]
    files = [root / name / "fisherrf" / "farthest" / "seed0.json"] if suite == "real6" else sorted(root.glob(f"{name}-*/*/seed0.json"))
    for path in files:
        if not path.is_file():
            continue
        run = json.loads(path.read_text())
        if run.get("protocol") == "fisherrf" and run.get("selector") == "farthest" and len(run.get("initial_views") or []) == 4 \
                and len(run.get("chosen_views") or []) >= 12:
            return {"source": str(path.relative_to(REPO)), "names": list(run["initial_views"]) + list(run["chosen_views"])}
    return None


def computed_order(cameras, num: int) -> List[int]:
    """The FisherRF protocol's views without a run: the datamanager's fps initial views (farthest_point_order from
    view 0, sorted), then FarthestSelector one view per round."""
    import torch

    from hpgs_ns.selectors.farthest import FarthestSelector, FarthestSelectorConfig, farthest_point_order

    active = sorted(farthest_point_order(cameras.camera_to_worlds[:, :3, 3], 4, start=0))
    order, selector = list(active), FarthestSelector(FarthestSelectorConfig())
    while len(order) < min(num, len(cameras)):
        candidates = [i for i in range(len(cameras)) if i not in order]
        context = SimpleNamespace(cameras=cameras, active=sorted(order), candidates=candidates, num_to_pick=1,
                                  generator=torch.Generator().manual_seed(0))
        order += selector.select(context).indices
    return order


def view_order(name: str, suite: str, scene, outputs, num: int) -> dict:
    from hpgs_ns.dataparser import view_name

    names = [view_name(p, scene.path) for p in outputs.image_filenames]
    found = committed_order(name, suite)
    if found is not None:
        return {"source": found["source"], "views": [names.index(n) for n in found["names"][:num]]}
    return {"source": "computed (fps initial views + farthest selector)", "views": computed_order(outputs.cameras, num)}


def scene_extent(points: np.ndarray) -> float:
    """Diagonal of the box between the 5th and 95th percentiles on each axis (COLMAP's far outliers excluded)."""
    low, high = np.percentile(points, [5, 95], axis=0)
    return float(np.linalg.norm(high - low))


def measure(outputs, views: List[int], settings, tree, extent: Optional[float]) -> dict:
    from triangulation_variants import triangulate_variant  # benchmarks/ is on sys.path when this script runs

    xyz, _, info = triangulate_variant(outputs.cameras, outputs.image_filenames, views, settings)
    row = {"views": len(views), "points": info.num_points, "ok": info.ok, "failed": info.failed, "seconds": info.seconds["total"],
           "stages": {k: v for k, v in info.seconds.items() if k != "total"}, "pairs_matched": info.pairs_matched,
           "mean_track_length": round(info.mean_track_length, 3), "mean_reprojection_error_px": round(info.mean_reprojection_error, 3)}
    if info.failed:
        row["message"] = info.message
    if tree is not None and len(xyz):
        distance = tree.query(xyz.numpy())[0] / extent
        row["median_distance"] = round(float(np.median(distance)), 5)
        row["within_1pct"] = round(float((distance < 0.01).mean()), 4)
    return row


def markdown_table(payload: dict, names: List[str], variants: List[str]) -> str:
    """One row per scene and variant: points (median distance, % of the extent) and seconds at each view count."""
    counts = sorted({int(r["views"]) for e in payload["scenes"].values() for v in e.get("results", {}).values() for r in v})
    lines = ["| scene | setting | " + " | ".join(f"{n} views: points (median %), s" for n in counts) + " |",
             "|---|---|" + "---|" * len(counts)]
    for name in names:
        results = payload["scenes"].get(name, {}).get("results", {})
        for variant in variants:
            rows = {int(r["views"]): r for r in results.get(variant, [])}
            cells = []
            for n in counts:
                r = rows.get(n)
                if r is None:
                    cells.append("")
                    continue
                dist = f" ({100 * r['median_distance']:.2f}%)" if "median_distance" in r else ""
                cells.append(f"{r['points']}{dist}, {r['seconds']:.1f}")
            lines.append(f"| {name} | {variant} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", default=TUNING + JUDGING)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--views", type=int, nargs="+", default=[4, 8, 16])
    ap.add_argument("--data-root", type=Path, default=Path(os.environ.get("HPGS_SHARED", REPO.parent / "shared")) / "data")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--table", action="store_true", help="print the JSON's results as a markdown table; measure nothing")
    args = ap.parse_args()
    if args.table:
        print(markdown_table(json.loads((args.out / "triangulation_yield.json").read_text()), args.scenes, args.variants))
        return

    from scipy.spatial import cKDTree
    from triangulation_variants import VariantSettings

    from hpgs_ns.scenes.triangulate import DEFAULT_MAX_IMAGE_SIZE, DEFAULT_MIN_POINTS, DEFAULT_SETTINGS, TriangulationSettings

    path = args.out / "triangulation_yield.json"
    payload = json.loads(path.read_text()) if path.is_file() else {}
    payload.update({
        "machine": f"{platform.machine()} cpu x{os.cpu_count()}", "omp_threads": os.environ.get("OMP_NUM_THREADS"),
        "max_image_size": DEFAULT_MAX_IMAGE_SIZE, "min_points": DEFAULT_MIN_POINTS, "tuning": TUNING, "judging": JUDGING,
        "default": dataclasses.asdict(DEFAULT_SETTINGS), "chosen": CHOSEN,
        "chosen_is_default": TriangulationSettings(**VARIANTS[CHOSEN]) == DEFAULT_SETTINGS,
        "variants": {k: {**dataclasses.asdict(VariantSettings()), **v} for k, v in VARIANTS.items()},
        "note": "one call from scratch per row (a temporary workspace: every view extracted, every pair matched); "
                "median_distance: median distance to the nearest point of the scene's COLMAP model (all photos), as a fraction "
                "of the scene extent (5th-95th percentile box diagonal), nerfstudio's normalised frame; within_1pct: fraction "
                "of points closer than 1% of the extent; fox has no COLMAP model (counts only)",
    })
    scenes = payload.setdefault("scenes", {})
    for name in args.scenes:
        suite, scene, outputs = load_scene(name, args.data_root)
        order = view_order(name, suite, scene, outputs, max(args.views))
        reference = outputs.metadata.get("points3D_xyz")
        tree = extent = None
        if reference is not None and len(reference):
            tree, extent = cKDTree(reference.numpy()), scene_extent(reference.numpy())
        entry = scenes.setdefault(name, {})
        entry.update({"suite": suite, "path": str(scene.path), "options": scene.option_dict(), "order": order,
                      "image_size": [int(outputs.cameras.width[0]), int(outputs.cameras.height[0])],
                      "training_views": len(outputs.image_filenames), "extent": extent})
        results = entry.setdefault("results", {})
        for variant in args.variants:
            settings = VariantSettings(**VARIANTS[variant])
            rows = {int(r["views"]): r for r in results.get(variant, [])}
            for n in args.views:
                rows[n] = measure(outputs, order["views"][:n], settings, tree, extent)
                r = rows[n]
                dist = f"{100 * r['median_distance']:5.2f}%" if "median_distance" in r else "   -  "
                print(f"{name:16s} {variant:14s} {n:3d} views: {r['points']:6d} points, median {dist}, {r['seconds']:6.2f} s"
                      f"{'  ' + r['message'] if r.get('failed') else ''}", flush=True)
            results[variant] = [rows[n] for n in sorted(rows)]
            write_json_atomic(path, payload)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
