"""nerfstudio's COLMAP dataparser, set up for Mip-NeRF 360 scene folders.

Three changes to the stock parser, each because `ns-train hpgs --data mipnerf360/kitchen` must work as typed:
- images are ordered by file name (the stock parser orders by COLMAP image id), so "every 8th image is a test
  view" is the Mip-NeRF 360 convention;
- a missing `images_N` folder is made without an interactive prompt (PIL, written to a temp folder then renamed);
- a bad path or a missing model is a one-line error naming what is missing and how to fix it;
- unreadable image files (truncated, empty) are dropped with one warning, after the train/test split is made,
  so a dropped frame never shifts which views are test views; too many is an error.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Type

import numpy as np
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from hpgs_ns.scenes.colmap_model import model_file
from hpgs_ns.errors import UserError

MAX_AUTO_RESOLUTION = 1600  # nerfstudio's rule for the automatic downscale factor


class SceneDataError(UserError, ValueError):
    """The scene folder is missing something the parser needs."""


@dataclass
class MipNerf360DataParserConfig(ColmapDataParserConfig):
    """COLMAP scene in the Mip-NeRF 360 layout (`images/`, `images_N/`, `sparse/0/`); every 8th image in
    file-name order is a test view."""

    _target: Type = field(default_factory=lambda: MipNerf360DataParser)
    colmap_path: Path = Path("sparse/0")
    eval_interval: int = 8
    load_3D_points: bool = True
    max_unreadable_fraction: float = 0.1
    """Drop unreadable (truncated, empty) image files with a warning while at most this fraction of the images
    are; more is an error."""


class MipNerf360DataParser(ColmapDataParser):
    """Stock COLMAP parser with file-name ordering, non-interactive downscaling and clear errors."""

    config: MipNerf360DataParserConfig
    _all_image_filenames: Optional[List[Path]] = None  # every frame of the model, file-name order, before dropping
    _kept: Optional[List[int]] = None  # positions in that list of the frames kept
    _unreadable: Optional[Dict[str, str]] = None  # image path -> problem, checked once for all splits

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs):
        self._check_scene_folder()
        return super()._generate_dataparser_outputs(split, **kwargs)

    def _check_scene_folder(self) -> None:
        data = Path(self.config.data)
        if not data.is_dir():
            raise SceneDataError(f"scene folder {data} does not exist; pass --data PATH to a Mip-NeRF 360 style scene")
        model = data / self.config.colmap_path
        if model_file(model, "cameras") is None:
            raise SceneDataError(
                f"no camera poses: {model}/cameras.bin (or .txt) is missing; run COLMAP first or set --colmap-path"
            )
        if model_file(model, "images") is None:
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
        self._all_image_filenames = [Path(f["file_path"]) for f in out["frames"]]
        bad = self._unreadable_positions([folder / Path(f["file_path"]).name for f in out["frames"]])
        self._kept = [i for i in range(len(out["frames"])) if i not in bad]
        out["frames"] = [out["frames"][i] for i in self._kept]
        return out

    def _unreadable_positions(self, paths: List[Path]) -> List[int]:
        """Positions of the unreadable files in `paths`; warns once (the parser runs once per split), raises
        SceneDataError when too many are unreadable or a split would be left empty."""
        first = self._unreadable is None
        if first:
            self._unreadable = {str(p): problem for p in paths if (problem := image_problem(p)) is not None}
        bad = [i for i, p in enumerate(paths) if str(p) in self._unreadable]
        if not bad:
            return bad
        names = ", ".join(f"{paths[i].name} ({self._unreadable[str(paths[i])]})" for i in bad[:8]) + (" ..." if len(bad) > 8 else "")
        full = self._all_image_filenames
        stock_split = ColmapDataParser._get_image_indices  # the split of every frame, before any is dropped
        empty = [s for s in ("train", "test") if set(np.asarray(stock_split(self, full, s)).tolist()) <= set(bad)]
        limit = self.config.max_unreadable_fraction
        if len(bad) > limit * len(paths) or empty:
            why = f"the {empty[0]} split would be empty" if empty else f"more than {limit:.0%} of {len(paths)}"
            raise SceneDataError(
                f"{len(bad)} unreadable images in {paths[0].parent} ({why}): {names}; restore them from the source "
                f"or raise --pipeline.datamanager.dataparser.max-unreadable-fraction"
            )
        if first:
            CONSOLE.print(f"[yellow]Dropping {len(bad)} of {len(paths)} images, unreadable: {names} (test split unchanged)", soft_wrap=True)
        return bad

    def _get_image_indices(self, image_filenames, split):
        """The stock split of every frame in the model, mapped onto the frames kept after dropping unreadable ones."""
        if self._all_image_filenames is None or self._kept is None or len(self._kept) != len(image_filenames):
            return super()._get_image_indices(image_filenames, split)
        position = {orig: k for k, orig in enumerate(self._kept)}
        indices = super()._get_image_indices(self._all_image_filenames, split)
        return np.array([position[int(i)] for i in indices if int(i) in position], dtype=np.int64)

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
            try:
                with Image.open(source / rel) as image:
                    size = (round_fn(image.width / factor), round_fn(image.height / factor))
                    resized = image.resize(size, Image.Resampling.BICUBIC)
            except (OSError, SyntaxError, ValueError) as err:  # PIL's errors for unreadable files
                raise SceneDataError(f"cannot read {source / rel} ({err}); restore it or remove it from the COLMAP model") from err
            out = tmp / rel
            out.parent.mkdir(parents=True, exist_ok=True)
            resized.save(out, quality=95)
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    except SceneDataError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    except OSError as err:
        shutil.rmtree(tmp, ignore_errors=True)
        raise SceneDataError(
            f"could not write {target} ({err}); make the folder writable or pass --downscale-factor 1"
        ) from err


def image_problem(path: Path) -> Optional[str]:
    """Why the image file at `path` cannot be used ("empty file", "truncated", PIL's error), or None.

    Cheap but real: JPEGs are decoded at 1/8 scale (`draft`), which still reads the whole entropy-coded stream;
    other formats are checked by PIL's `verify()` (for PNG: every chunk and its CRC, up to IEND)."""
    try:
        if path.stat().st_size == 0:
            return "empty file"
        with Image.open(path) as image:
            if image.format == "JPEG":
                image.draft("RGB", (max(image.width // 8, 1), max(image.height // 8, 1)))
                image.load()
            else:
                image.verify()
    except Exception as err:  # PIL raises OSError, SyntaxError, struct.error, ... for damaged files
        return "truncated" if "truncated" in str(err).lower() else (str(err) or type(err).__name__)
    return None
