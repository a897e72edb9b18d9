"""Does a trainer arm's gain on a test view follow how far that view is from the run's training views?

For each scene and seed with runs of both ARM and BASE (`<root>/<scene>/<arm>/farthest/seed<k>.json`), pairs the
per-test-view PSNR (`test_views`) and relates the difference to the view's distance to the nearest of the run's
final training views (camera centres from the scene's COLMAP model in ../shared/data/<scene>/sparse/0, divided by the
scene's median) and to the smallest angle between viewing directions. A gain that comes from seed points covering
what no training view sees would grow with both; a cleaner splat would give an even gain.

    python benchmarks/per_view_gain_vs_distance.py --arm colmap-r20 --base colmap [--root benchmarks/results/tune-full]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def cameras(scene: str):
    """{image name as the runs write it: (centre [3], viewing direction [3])} from the scene's COLMAP model."""
    import pycolmap

    model = DATA / scene / "sparse" / "0"
    if not model.is_dir():
        raise SystemExit(f"{model} is missing: this needs ../shared/data/{scene} (COLMAP scenes only)")
    rec = pycolmap.Reconstruction(str(model))
    return {f"images/{im.name}": (np.asarray(im.projection_center()), np.asarray(im.cam_from_world().rotation.matrix())[2])
            for im in rec.images.values()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("benchmarks/results/tune-full"))
    parser.add_argument("--arm", required=True)
    parser.add_argument("--base", required=True)
    args = parser.parse_args()
    pooled = []
    for scene_dir in sorted(p for p in args.root.iterdir() if (p / args.arm).is_dir() and (p / args.base).is_dir()):
        cams, rows = cameras(scene_dir.name), []
        for path in sorted((scene_dir / args.arm / "farthest").glob("seed*.json")):
            other = scene_dir / args.base / "farthest" / path.name
            if not other.exists():
                continue
            arm, base = json.loads(path.read_text()), json.loads(other.read_text())
            train = [cams[n] for n in arm["initial_views"] + arm["chosen_views"] if n in cams]
            before = {v["name"]: v["psnr"] for v in base["test_views"]}
            for view in arm["test_views"]:
                if view["name"] in cams and view["name"] in before:
                    centre, forward = cams[view["name"]]
                    distance = min(np.linalg.norm(centre - c) for c, _ in train)
                    angle = min(np.degrees(np.arccos(np.clip(forward @ f, -1, 1))) for _, f in train)
                    rows.append([distance, angle, view["psnr"] - before[view["name"]]])
        if not rows:
            continue
        rows = np.asarray(rows)
        rows[:, 0] /= np.median(rows[:, 0])
        pooled.append(rows)
        print(f"{scene_dir.name:16s} {len(rows):3d} views  gain {rows[:, 2].mean():+.2f} dB  Spearman with distance "
              f"{spearmanr(rows[:, 0], rows[:, 2])[0]:+.2f}, with angle {spearmanr(rows[:, 1], rows[:, 2])[0]:+.2f}")
    if not pooled:
        raise SystemExit(f"no scene under {args.root} has farthest runs of both {args.arm} and {args.base}")
    rows = np.concatenate(pooled)
    rho_d, p_d = spearmanr(rows[:, 0], rows[:, 2])
    rho_a, p_a = spearmanr(rows[:, 1], rows[:, 2])
    far = rows[:, 1] > np.median(rows[:, 1])
    print(f"all {len(rows)} views: Spearman with distance {rho_d:+.2f} (p {p_d:.2f}), with angle {rho_a:+.2f} (p {p_a:.2f}); "
          f"gain on the views farther in angle than the median {rows[far, 2].mean():+.2f} dB, nearer {rows[~far, 2].mean():+.2f}")


if __name__ == "__main__":
    main()
