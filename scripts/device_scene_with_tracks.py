"""Make a copy of a COLMAP scene small enough to carry to the GPU machine that still has its point tracks.

`--strict-init` needs each seed point's track (which images see it); the shared bonsai-device copy dropped them
with the 2D keypoints. This keeps every 3D point and its track, drops only the keypoints from images.bin (the
dataparser reads neither unless `max-2D-matches-per-3D-point` is set), and copies the `images_N` folder of a
scene that already has it:

    python scripts/device_scene_with_tracks.py ../shared/data/mipnerf360-bonsai \
        ../shared/data/mipnerf360-bonsai-device/images_2 .dev-tracks/bonsai
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
from nerfstudio.data.utils import colmap_parsing_utils as colmap_utils


def write_images_without_keypoints(src: Path, dst: Path) -> None:
    images = colmap_utils.read_images_binary(src)
    none = dict(xys=np.zeros((0, 2)), point3D_ids=np.zeros(0, dtype=np.int64))
    colmap_utils.write_images_binary({k: im._replace(**none) for k, im in images.items()}, dst)


def main(scene: Path, images_dir: Path, out: Path) -> None:
    model = scene / "sparse" / "0"
    if not (model / "points3D.bin").exists() or not (model / "images.bin").exists():
        raise SystemExit(f"{model} has no images.bin/points3D.bin; pass a scene folder with a binary COLMAP model")
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "sparse" / "0").mkdir(parents=True)
    shutil.copy(model / "cameras.bin", tmp / "sparse" / "0")
    shutil.copy(model / "points3D.bin", tmp / "sparse" / "0")
    write_images_without_keypoints(model / "images.bin", tmp / "sparse" / "0" / "images.bin")
    shutil.copytree(images_dir, tmp / images_dir.name)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    print(f"{out}: {sum(p.stat().st_size for p in out.rglob('*') if p.is_file()) / 2**20:.1f} MiB")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    main(*map(Path, sys.argv[1:]))
