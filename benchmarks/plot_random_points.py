"""Top view of where a random start puts its points: COLMAP's (all photos), `random-points views` along the FisherRF
start's 4 farthest views (in their pixels' colours), and splatfacto's cube of side 2, on bonsai, figurine-desk and
fox (no COLMAP points). Writes docs/random-points-views.png.

    python benchmarks/plot_random_points.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib
import numpy as np
import torch
from PIL import Image

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from random_start_coverage import outputs  # noqa: E402

from hpgs_ns.atomic_write import atomic_path  # noqa: E402
from hpgs_ns.scenes.view_points import points_along_views  # noqa: E402
from hpgs_ns.selectors.farthest import farthest_point_order  # noqa: E402

SCENES = [("bonsai", "mipnerf360-bonsai-device", "mipnerf360"), ("figurine-desk", "figurine-desk", "mipnerf360"),
          ("fox", "fox-nerfstudio", "nerfstudio-data")]


def photo(parsed, view: int) -> np.ndarray:
    """A training photo at its camera's size."""
    size = (int(parsed.cameras.width[view]), int(parsed.cameras.height[view]))
    return np.asarray(Image.open(parsed.image_filenames[view]).convert("RGB").resize(size))


def main(data_root: Path = Path("../shared/data"), out: Path = Path("docs/random-points-views.png")) -> None:
    fig, axes = plt.subplots(1, len(SCENES), figsize=(15, 5))
    for ax, (name, folder, kind) in zip(axes, SCENES):
        parsed = outputs(data_root / folder, kind)
        cameras = parsed.cameras
        centres = cameras.camera_to_worlds[:, :3, 3]
        views = sorted(farthest_point_order(centres, 4, start=0))

        xyz, rgb = points_along_views(cameras, lambda view, parsed=parsed: photo(parsed, view), views, 20000,
                                      torch.Generator().manual_seed(0))
        colmap = parsed.metadata.get("points3D_xyz")
        if colmap is not None:
            ax.scatter(colmap[:, 0], colmap[:, 1], s=0.3, c="0.6", label="COLMAP points (all photos)")
        ax.scatter(xyz[:, 0], xyz[:, 1], s=0.3, c=rgb.numpy() / 255, label="random-points views (4 initial views)")
        cube = (np.random.default_rng(0).random((5000, 3)) - 0.5) * 2
        ax.scatter(cube[:, 0], cube[:, 1], s=0.3, c="tab:red", alpha=0.3, label="cube of side 2")
        ax.scatter(centres[:, 0], centres[:, 1], s=6, c="k", marker="^", label="cameras")
        ax.scatter(centres[views, 0], centres[views, 1], s=40, c="blue", marker="^", label="4 initial views")
        ax.set_xlim(-3, 3)
        ax.set_ylim(-3, 3)
        ax.set_aspect("equal")
        ax.set_title(f"{name} (top view, x-y)")
    axes[0].legend(loc="lower left", fontsize=7, markerscale=5)
    fig.tight_layout()
    with atomic_path(out, suffix=Path(out).suffix) as tmp:  # no half-written figure
        fig.savefig(tmp, dpi=60)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
