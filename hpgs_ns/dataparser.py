"""nerfstudio's COLMAP dataparser, set up for Mip-NeRF 360 scene folders.

Three changes to the stock parser, each because `ns-train hpgs --data mipnerf360/kitchen` must work as typed:
- images are ordered by file name (the stock parser orders by COLMAP image id), so "every 8th image is a test
  view" is the Mip-NeRF 360 convention;
- a missing `images_N` folder is made without an interactive prompt (PIL, written to a temp folder then renamed);
- a bad path or a missing model is a one-line error naming what is missing and how to fix it.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Type

from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

MAX_AUTO_RESOLUTION = 1600  # nerfstudio's rule for the automatic downscale factor


class SceneDataError(ValueError):
    """The scene folder is missing something the parser needs."""


@dataclass
class MipNerf360DataParserConfig(ColmapDataParserConfig):
    """COLMAP scene in the Mip-NeRF 360 layout (`images/`, `images_N/`, `sparse/0/`); every 8th image in
    file-name order is a test view."""

    _target: Type = field(default_factory=lambda: MipNerf360DataParser)
    colmap_path: Path = Path("sparse/0")
    eval_interval: int = 8
    load_3D_points: bool = True


class MipNerf360DataParser(ColmapDataParser):
    """Stock COLMAP parser with file-name ordering, non-interactive downscaling and clear errors."""

    config: MipNerf360DataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs):
        self._check_scene_folder()
        return super()._generate_dataparser_outputs(split, **kwargs)

    def _check_scene_folder(self) -> None:
        data = Path(self.config.data)
        if not data.is_dir():
            raise SceneDataError(f"scene folder {data} does not exist; pass --data PATH to a Mip-NeRF 360 style scene")
        model = data / self.config.colmap_path
        if not ((model / "cameras.bin").exists() or (model / "cameras.txt").exists()):
            raise SceneDataError(
                f"no camera poses: {model}/cameras.bin (or .txt) is missing; run COLMAP first or set --colmap-path"
            )
        if not ((model / "images.bin").exists() or (model / "images.txt").exists()):
            raise SceneDataError(f"no camera poses: {model}/images.bin (or .txt) is missing; run COLMAP first")
        if not self._image_folder().is_dir():
            raise SceneDataError(f"image folder {self._image_folder()} does not exist; set --images-path or --downscale-factor")

    def _image_folder(self) -> Path:
        """Where the photos are read from: `images/`, or `images_N/` when a downscale factor N is given."""
        folder = Path(self.config.data) / self.config.images_path
        factor = self.config.downscale_factor
        return folder.parent / f"{folder.name}_{factor}" if factor and factor > 1 else folder

    def _get_all_images_and_cameras(self, recon_dir: Path):
        out = super()._get_all_images_and_cameras(recon_dir)
        out["frames"] = sorted(out["frames"], key=lambda frame: Path(frame["file_path"]).name)
        folder = self._image_folder()
        missing = [str(folder / Path(f["file_path"]).name) for f in out["frames"] if not (folder / Path(f["file_path"]).name).exists()]
        if missing:
            raise SceneDataError(
                f"{len(missing)} images named in the COLMAP model are missing, e.g. {missing[0]}; restore them or re-run COLMAP"
            )
        return out

    def _setup_downscale_factor(self, image_filenames: List[Path], mask_filenames: List[Path], depth_filenames: List[Path]):
        if self._downscale_factor is None:
            factor = self.config.downscale_factor
            if factor is None:
                width, height = Image.open(next(iter(image_filenames))).size
                factor = 1
                while max(width, height) / factor > MAX_AUTO_RESOLUTION:
                    factor *= 2
            if factor > 1:
                source = self.config.data / self.config.images_path
                _make_downscaled_folder(source, image_filenames, factor, self.config.downscale_rounding_mode)
        return super()._setup_downscale_factor(image_filenames, mask_filenames, depth_filenames)


def _make_downscaled_folder(source: Path, image_filenames: List[Path], factor: int, rounding: str) -> None:
    """Write `images_N` beside `images` if it is missing or incomplete, atomically (temp folder, then rename)."""
    target = source.parent / f"{source.name}_{factor}"
    wanted = [Path(p).relative_to(source) for p in image_filenames]
    if target.is_dir() and all((target / rel).exists() for rel in wanted):
        return
    CONSOLE.print(f"[yellow]Writing {target.name}/ ({len(wanted)} images downscaled {factor}x)")
    round_fn = {"floor": int, "round": round, "ceil": lambda v: -int(-v // 1)}[rounding]
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=source.parent))
    try:
        for rel in wanted:
            with Image.open(source / rel) as image:
                size = (round_fn(image.width / factor), round_fn(image.height / factor))
                out = tmp / rel
                out.parent.mkdir(parents=True, exist_ok=True)
                image.resize(size, Image.Resampling.BICUBIC).save(out, quality=95)
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    except OSError as err:
        shutil.rmtree(tmp, ignore_errors=True)
        raise SceneDataError(
            f"could not write {target} ({err}); make the folder writable or pass --downscale-factor 1"
        ) from err
