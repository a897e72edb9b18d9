"""Copies of a suite's scenes small enough to carry to the GPU machine, under .devdata/ (git-ignored).

COLMAP scenes keep their images_2/ and their model with every 3D point and its track, but no 2D keypoints
(`device_scene_with_tracks.py`: the dataparser never reads them); fox (nerfstudio-data) gets transforms.json and
an images_2/ written as its dataparser would (floor rounding). Carry `.devdata/<folder>` per scene a call needs
and run `hpgs bench --suite real12 --data-root .devdata --suite-scenes NAME ...` there; `--suite-scenes` here copies
only those (a call carries one to three scenes).

    python scripts/device_suite_data.py [--suite real6] [--suite-scenes NAME ...] [--data-root ../shared/data] [--out .devdata]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from device_scene_with_tracks import main as colmap_copy  # noqa: E402
from PIL import Image  # noqa: E402

from hpgs_lab.suites import load_suite  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="real6")
    ap.add_argument("--suite-scenes", nargs="+", default=[], help="only these scenes of the suite (default: all)")
    ap.add_argument("--data-root", type=Path, default=Path("../shared/data"))
    ap.add_argument("--out", type=Path, default=Path(".devdata"))
    args = ap.parse_args()
    for scene in load_suite(args.suite, args.data_root, args.suite_scenes):
        if scene.smoke:
            continue
        factor = int(scene.option_dict().get("downscale-factor", 1))
        dest = args.out / scene.path.name
        if dest.exists():
            print(f"{dest}: exists")
            continue
        if scene.dataparser == "nerfstudio-data":
            tmp = dest.with_name(dest.name + ".tmp")
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            shutil.copy(scene.path / "transforms.json", tmp)
            (tmp / f"images_{factor}").mkdir()
            for frame in json.loads((scene.path / "transforms.json").read_text())["frames"]:
                source = scene.path / frame["file_path"]
                with Image.open(source) as im:  # nerfstudio's camera rescale floors: so do the images
                    im.resize((im.width // factor, im.height // factor), Image.Resampling.BICUBIC).save(
                        tmp / f"images_{factor}" / source.name, quality=95)
            tmp.rename(dest)
        else:
            colmap_copy(scene.path, scene.path / f"images_{factor}", dest)
        print(f"{dest}: {sum(p.stat().st_size for p in dest.rglob('*') if p.is_file()) / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
