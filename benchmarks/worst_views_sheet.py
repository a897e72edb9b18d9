"""A contact sheet of the runs' worst test views: each result's `seed<k>-worst0.jpg` (ground truth | render, kept by
`hpgs bench` since 0.4) with its scene, folder, seed, view and PSNR, so a floater that moves a scene's mean can be
seen, not only counted.

    python benchmarks/worst_views_sheet.py benchmarks/results/tune-full [--rank 0] [--out worst_views.png]
        [--scenes a,b] [--arms active,active-r20] [--seeds 0] [--near 0.8]

`--near R` keeps only the worst views whose render depth (10th percentile over opaque pixels) is below R times the
same view's in the run's final-set (`final-set/seed<k>.json` beside the run): views with something in front of the
camera that the final-set has not.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from PIL import Image  # noqa: E402

from hpgs_ns.atomic_write import atomic_path  # noqa: E402


def final_set_view(result: Path, name: str):
    """The test view `name` in the final-set beside run `result` (a dict), or None."""
    path = result.parent / "final-set" / result.name
    if result.parent.name == "final-set" or not path.is_file():
        return None
    return next((v for v in json.loads(path.read_text()).get("test_views", []) if v["name"] == name), None)


def entries(root: Path, rank: int, scenes=None, arms=None, seeds=None, near=None):
    """(title, image path) for every result under `root` (<scene>/<arm>/<selector>/seed<k>.json; None: any) that kept
    a worst view of this rank, sorted by its PSNR; with `near`, only views nearer than `near` x their final-set's."""
    found = []
    for result in sorted(root.rglob("seed*.json")):
        parts = result.relative_to(root).parts
        if (scenes and parts[0] not in scenes) or (arms and (len(parts) < 4 or parts[1] not in arms)):
            continue
        try:
            data = json.loads(result.read_text())
        except ValueError:
            continue
        worst = data.get("worst_views") or []
        if len(worst) <= rank or not (result.parent / worst[rank]["image"]).is_file():
            continue
        if seeds is not None and data.get("seed") not in seeds:
            continue
        view = worst[rank]
        label = "/".join(result.relative_to(root).parts[:-1])
        title = f"{label} s{data['seed']}\n{Path(view['name']).name}: {view['psnr']:.1f} dB (mean {data['test']['psnr']:.1f})"
        if near is not None:
            mine = next((v for v in data.get("test_views", []) if v["name"] == view["name"]), {})
            theirs = final_set_view(result, view["name"])
            if not theirs or mine.get("depth_p10") is None or theirs.get("depth_p10") is None \
                    or mine["depth_p10"] >= near * theirs["depth_p10"]:
                continue
            title += (f"; final-set {theirs['psnr']:.1f} dB\ndepth p10 {mine['depth_p10']:.2f} "
                      f"(final-set {theirs['depth_p10']:.2f})")
            if mine.get("front_cover") is not None and theirs.get("front_cover") is not None:
                title += f"; in front cover {mine['front_cover']:.0%} ({theirs['front_cover']:.0%})"
        found.append((view["psnr"], title, result.parent / view["image"]))
    return [(title, path) for _, title, path in sorted(found)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("--rank", type=int, default=0, help="0: each run's worst view, 1: its second worst")
    parser.add_argument("--columns", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None, help="default: ROOT/worst_views.png")
    parser.add_argument("--scenes", default="", help="comma-separated scene folders (default: all)")
    parser.add_argument("--arms", default="", help="comma-separated arm folders, the level under the scene (default: all)")
    parser.add_argument("--seeds", default="", help="comma-separated seeds (default: all)")
    parser.add_argument("--near", type=float, default=None,
                        help="only views whose depth p10 is below this times their final-set's (e.g. 0.8)")
    args = parser.parse_args()
    split = lambda text: [t for t in text.split(",") if t] or None  # noqa: E731
    seeds = split(args.seeds)
    items = entries(args.root, args.rank, split(args.scenes), split(args.arms), seeds and [int(s) for s in seeds],
                    args.near)
    if not items:
        raise SystemExit(f"no worst-view JPEGs under {args.root} (runs written by hpgs bench >= 0.4 keep them)")
    rows = math.ceil(len(items) / args.columns)
    fig, axes = plt.subplots(rows, args.columns, figsize=(5 * args.columns, 2.6 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (title, path) in zip(axes.flat, items):
        ax.imshow(Image.open(path))
        ax.set_title(title, fontsize=7)
    fig.tight_layout()
    out = args.out or args.root / "worst_views.png"
    with atomic_path(out, suffix=Path(out).suffix) as tmp:  # no half-written figure
        fig.savefig(tmp, dpi=90)
    print(f"{len(items)} runs -> {out}")


if __name__ == "__main__":
    main()
