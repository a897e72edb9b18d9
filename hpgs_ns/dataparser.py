"""The dataparsers `ns-train hpgs` takes: nerfstudio's, as a subcommand, with Mip-NeRF 360 COLMAP as the default.

`ns-train hpgs --data mipnerf360/kitchen` uses `mipnerf360` (below); `ns-train hpgs [options] nerfstudio-data
--data capture/` a `transforms.json` folder from `ns-process-data`, Polycam, Record3D or instant-ngp; `colmap`,
`blender-data` and every other parser nerfstudio (or one of its plugins) registers are there too, as for
`ns-train splatfacto`. Parser options follow the subcommand: `ns-train hpgs [options] mipnerf360
--downscale-factor 2`. Each parser keeps its own train/test split.

`mipnerf360` is nerfstudio's COLMAP parser with four changes, each because `ns-train hpgs --data
mipnerf360/kitchen` must work as typed:
- images are ordered by file name (the stock parser orders by COLMAP image id), so "every 8th image is a test
  view" is the Mip-NeRF 360 convention;
- a missing `images_N` folder (for the automatic factor or an explicit `--downscale-factor N`) is made without an
  interactive prompt (PIL, written to a temp folder then renamed), and images whose size does not match their
  cameras' are a one-line error naming the rounding mode that fits;
- a scene without `images/` but with one `images_N/` (many downloaded scenes) is read from `images_N/` at factor N,
  said in one line; with several, the one the automatic factor's rule picks;
- a bad path or a missing model is a one-line error naming what is missing and how to fix it;
- unreadable image files (truncated, empty) are dropped with one warning, after the train/test split is made,
  so a dropped frame never shifts which views are test views; too many is an error.

`nerfstudio-data` is nerfstudio's parser loading the capture's seed points (`ply_file_path` in transforms.json,
or `sparse_pc.ply`) as splatfacto's does, read with `plyfile` instead of open3d (which needs a system library
that is often missing), and without its interactive prompt.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Type

import numpy as np
import torch
import tyro
from nerfstudio.configs.dataparser_configs import all_dataparsers
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from hpgs_ns.errors import UserError, check_option
from hpgs_ns.image_files import image_problem
from hpgs_ns.scenes.colmap_model import ColmapModelError, check_model, model_file

MAX_AUTO_RESOLUTION = 1600  # nerfstudio's rule for the automatic downscale factor
# nerfstudio's --downscale-rounding-mode (colmap_dataparser.calculate_scaled_size)
ROUNDING = {"floor": math.floor, "round": round, "ceil": math.ceil}


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

    def __post_init__(self) -> None:
        check_parser_values(self, "mipnerf360")
        check_option("mipnerf360 --max-unreadable-fraction", self.max_unreadable_fraction,
                     0 <= self.max_unreadable_fraction <= 1, "must be within [0, 1]", "pass e.g. 0.1 (the default)")


def check_data_path(data: Path, colmap_path: Path = Path("sparse/0"), images_path: Path = Path("images")) -> None:
    """SceneDataError when `--data` names a file or nothing (run while the command line is parsed, too)."""
    if data.is_file():
        scene = next((p for p in data.parents if (p / colmap_path).is_dir()), None)
        if data.name == "transforms.json":
            fix = f"run: ns-train hpgs [options] nerfstudio-data --data {data.parent}"
        elif scene is not None:
            fix = f"pass --data {scene}"
        else:
            fix = f"pass --data the scene folder (the one holding {images_path}/ and {colmap_path}/)"
        raise SceneDataError(f"--data {data} is a file, not a scene folder; {fix}")
    if not data.is_dir():
        raise SceneDataError(f"scene folder {data} does not exist; pass --data PATH to a Mip-NeRF 360 style scene")


def check_parser_values(config, subcommand: str) -> None:
    """The dataparser options whose values make no sense, as a one-line `OptionError` while tyro parses them."""
    check_option(f"{subcommand} --downscale-factor", config.downscale_factor,
                 config.downscale_factor is None or config.downscale_factor >= 1, "must be at least 1",
                 "pass 1, 2, 4, ... or leave it out (automatic)")
    check_option(f"{subcommand} --eval-interval", config.eval_interval, config.eval_interval >= 1,
                 "must be at least 1 (every Nth image is a test view)", "pass e.g. 8")
    fraction = config.train_split_fraction
    check_option(f"{subcommand} --train-split-fraction", fraction,
                 0 < fraction < 1 or (config.eval_mode != "fraction" and 0 < fraction <= 1),
                 "must be within (0, 1) (the rest are test views)", "pass e.g. 0.9")


class MipNerf360DataParser(ColmapDataParser):
    """Stock COLMAP parser with file-name ordering, non-interactive downscaling and clear errors."""

    config: MipNerf360DataParserConfig
    _all_image_filenames: Optional[List[Path]] = None  # every frame of the model, file-name order, before dropping
    _kept: Optional[List[int]] = None  # positions in that list of the frames kept
    _unreadable: Optional[Dict[str, str]] = None  # image path -> problem, checked once for all splits
    _model_checked: bool = False  # the COLMAP model's files read without error (check_model)

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs):
        self._check_scene_folder()
        self._use_the_only_downscaled_folder()
        try:
            outputs = super()._generate_dataparser_outputs(split, **kwargs)
        except (KeyError, IndexError, TypeError, NotImplementedError, AssertionError) as err:
            # the model's files read (checked above) but nerfstudio cannot use what they say (a camera model it
            # does not support, an image id no camera has, ...); HPGS_TRACEBACK=1 shows where
            model = Path(self.config.data) / self.config.colmap_path
            raise SceneDataError(f"the COLMAP model {model} cannot be used ({type(err).__name__}: "
                                 f"{str(err).splitlines()[0][:120] if str(err) else 'no detail'}); re-run COLMAP "
                                 "(pinhole or radial cameras)") from err
        self._check_image_size(outputs)
        return outputs

    def _check_image_size(self, outputs) -> None:
        """The first image's size must be its camera's (nerfstudio asserts it deep in image loading)."""
        if not outputs.image_filenames:
            return
        path = Path(outputs.image_filenames[0])
        with Image.open(path) as image:
            size = image.size
        camera = (int(outputs.cameras.width[0]), int(outputs.cameras.height[0]))
        if size == camera:
            return
        factor = self._downscale_factor or 1
        full = Path(self.config.data) / self.config.images_path / path.name
        fits = []
        if factor > 1 and full.is_file():
            with Image.open(full) as image:
                width, height = image.size
            fits = [mode for mode, fn in ROUNDING.items() if (fn(width / factor), fn(height / factor)) == size]
        model = f"the COLMAP model ({Path(self.config.data) / self.config.colmap_path})"
        folder = Path(self.config.images_path)
        named = _RESOLUTION_FOLDER.match(folder.name)
        if factor == 1 and named and _shrunk_by(size, camera) == int(named.group(1)):
            # `--images-path images_N`: photos at 1/N of their cameras' size; only --downscale-factor scales cameras
            n = int(named.group(1))
            base = folder.parent / "images"
            images = "" if base == Path("images") else f" --images-path {base}"
            raise SceneDataError(f"{path} is {size[0]}x{size[1]} but its camera says {camera[0]}x{camera[1]}: {path.parent} "
                                 f"holds the photos at 1/{n} of their cameras' size; pass mipnerf360 --downscale-factor {n}"
                                 f"{images} instead of --images-path {folder} (it reads {path.parent} and scales the "
                                 "cameras to it)")
        if fits:
            fix = f"pass mipnerf360 --downscale-rounding-mode {fits[0]}"
        elif _RESOLUTION_FOLDER.match(path.parent.name):
            fix = downscaled_fix(path, camera, model)
            if not fix.startswith("delete"):  # the source photo is the wrong size, not the rounding
                raise SceneDataError(f"{path} is {size[0]}x{size[1]} but its camera says {camera[0]}x{camera[1]}; {fix}")
        else:  # a full-resolution photo: no rounding is involved
            raise SceneDataError(f"{path} is {size[0]}x{size[1]} but its camera says {camera[0]}x{camera[1]}; replace it "
                                 f"with the {camera[0]}x{camera[1]} photo its camera was made from, or remove it from {model}")
        raise SceneDataError(
            f"{path} is {size[0]}x{size[1]} but its camera says {camera[0]}x{camera[1]} ({path.parent} was not made with "
            f"--downscale-rounding-mode {self.config.downscale_rounding_mode}); {fix}"
        )

    def _check_scene_folder(self) -> None:
        data = Path(self.config.data)
        check_data_path(data, self.config.colmap_path, self.config.images_path)
        model = data / self.config.colmap_path
        if model_file(model, "cameras") is None:
            if (data / "transforms.json").is_file():
                raise SceneDataError(
                    f"{data} is a nerfstudio-data folder (transforms.json, no COLMAP model); "
                    f"run: ns-train hpgs [options] nerfstudio-data --data {data}"
                )
            raise SceneDataError(
                f"no camera poses: {model}/cameras.bin (or .txt) is missing; run COLMAP first or set --colmap-path"
            )
        if model_file(model, "images") is None:
            raise SceneDataError(f"no camera poses: {model}/images.bin (or .txt) is missing; run COLMAP first")
        if not self._model_checked:  # once for both splits; nerfstudio's readers raise struct.error on a truncated file
            try:
                check_model(model, points=self.config.load_3D_points)
            except ColmapModelError as err:
                raise SceneDataError(str(err)) from err
            self._model_checked = True
        full = data / self.config.images_path
        if not self._image_folder().is_dir() and not full.is_dir():  # images_N is written from images/
            found = self._downscaled_folders()
            if self.config.downscale_factor is None and found:
                return  # read from one of them (_use_the_only_downscaled_folder)
            if found:  # --downscale-factor N with no images_N and no images/ to write it from
                factors = " or ".join(str(n) for n in found)
                raise SceneDataError(f"{self._image_folder()} does not exist and there is no {full} to write it from; "
                                     f"the photos are in {', '.join(str(f) for f in found.values())}: pass mipnerf360 "
                                     f"--downscale-factor {factors}")
            raise SceneDataError(f"image folder {full} does not exist; set --images-path")

    def _downscaled_folders(self) -> Dict[int, Path]:
        """{N: the `images_N/` folder} beside the images folder (N > 1), smallest N first."""
        full = Path(self.config.data) / self.config.images_path
        if not full.parent.is_dir():
            return {}
        pattern = re.compile(rf"{re.escape(full.name)}_(\d+)")
        found = {int(m.group(1)): p for p in full.parent.iterdir() if (m := pattern.fullmatch(p.name)) and p.is_dir()}
        return {n: found[n] for n in sorted(found) if n > 1}

    def _use_the_only_downscaled_folder(self) -> None:
        """No `images/` but `images_N/` (downloaded scenes often ship only those): read `images_N/` at factor N
        (the cameras scaled by 1/N, as `--downscale-factor N` does) rather than stop, and say so once. With several,
        the smallest N whose photos fit nerfstudio's automatic rule (long side <= 1600 px), else the largest."""
        full = Path(self.config.data) / self.config.images_path
        if self.config.downscale_factor is not None or self._downscale_factor is not None or full.is_dir():
            return
        found = self._downscaled_folders()
        if not found:
            return
        chosen = max(found)
        for n, folder in found.items():
            photo = next((p for p in sorted(folder.iterdir()) if p.is_file() and image_problem(p) is None), None)
            if photo is not None:
                with Image.open(photo) as image:
                    if max(image.size) <= MAX_AUTO_RESOLUTION:
                        chosen = n
                        break
        self._downscale_factor = chosen
        others = f" (of {', '.join(p.name for p in found.values())})" if len(found) > 1 else ""
        CONSOLE.print(f"[yellow]{full} does not exist: reading the photos in {found[chosen]}{others}, with the cameras "
                      f"scaled to them (as mipnerf360 --downscale-factor {chosen})", soft_wrap=True)

    def _image_folder(self) -> Path:
        """Where the photos are read from: `images/`, or `images_N/` when a downscale factor N is given (or
        found: `_use_the_only_downscaled_folder`)."""
        folder = Path(self.config.data) / self.config.images_path
        factor = self.config.downscale_factor or self._downscale_factor
        return folder.parent / f"{folder.name}_{factor}" if factor and factor > 1 else folder

    def _get_all_images_and_cameras(self, recon_dir: Path):
        out = super()._get_all_images_and_cameras(recon_dir)
        out["frames"] = sorted(out["frames"], key=lambda frame: Path(frame["file_path"]).name)
        folder, full = self._image_folder(), Path(self.config.data) / self.config.images_path

        def source(frame) -> Path:
            # images_N is (re)written from the full-resolution images below; one missing there (dropped as unreadable
            # when images_N was written) is read, and checked, at full resolution
            name = Path(frame["file_path"]).name
            # without images/ (only images_N), a photo missing from images_N is named there
            return folder / name if (folder / name).exists() or not full.is_dir() else full / name

        paths = [source(f) for f in out["frames"]]
        missing = [str(p) for p in paths if not p.exists()]
        if missing:
            raise SceneDataError(
                f"{len(missing)} images named in the COLMAP model are missing, e.g. {missing[0]}; restore them or re-run COLMAP"
            )
        self._all_image_filenames = [Path(f["file_path"]) for f in out["frames"]]
        bad = self._unreadable_positions(paths)
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
                f"or raise mipnerf360 --max-unreadable-fraction"
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
                with Image.open(next(iter(image_filenames))) as image:
                    width, height = image.size
                factor = 1
                while max(width, height) / factor > MAX_AUTO_RESOLUTION:
                    factor *= 2
            if factor > 1:
                source = self.config.data / self.config.images_path
                _make_downscaled_folder(source, image_filenames, factor, self.config.downscale_rounding_mode)
        return super()._setup_downscale_factor(image_filenames, mask_filenames, depth_filenames)


def _make_downscaled_folder(source: Path, image_filenames: List[Path], factor: int, rounding: str,
                            model: str = "the COLMAP model") -> None:
    """Write `images_N` beside `images` if it is missing or incomplete, atomically (temp folder, then rename).
    `model`: what names the images (an unreadable one's fix is to remove it from there)."""
    target = source.parent / f"{source.name}_{factor}"
    wanted = [Path(p).relative_to(source) for p in image_filenames]
    if target.is_dir() and all((target / rel).exists() for rel in wanted):
        return
    CONSOLE.print(f"[yellow]Writing {target.name}/ ({len(wanted)} images downscaled {factor}x)")
    round_fn = ROUNDING[rounding]
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=source.parent))
    try:
        for rel in wanted:
            try:
                with Image.open(source / rel) as image:
                    size = (round_fn(image.width / factor), round_fn(image.height / factor))
                    resized = image.resize(size, Image.Resampling.BICUBIC)
            except (OSError, SyntaxError, ValueError) as err:  # PIL's errors for unreadable files
                raise SceneDataError(f"cannot read {source / rel} ({err}); restore it or remove it from {model}") from err
            out = tmp / rel
            out.parent.mkdir(parents=True, exist_ok=True)
            resized.save(out, quality=95)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; the folder is the scene's, like images/
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    except SceneDataError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    except OSError as err:
        shutil.rmtree(tmp, ignore_errors=True)
        raise SceneDataError(
            f"could not write {target} ({err}); make the folder writable or pass the dataparser's --downscale-factor 1"
        ) from err


def check_image_sizes(datasets, parser_config) -> None:
    """Every photo of `datasets` (nerfstudio InputDatasets) must be its camera's size (nerfstudio asserts it, mid-run,
    when it first loads the photo); a one-line SceneDataError naming the first that is not. Reads headers only."""
    bad = []
    for dataset in datasets:
        scale, cameras = float(getattr(dataset, "scale_factor", 1.0)), dataset.cameras
        for i, path in enumerate(dataset.image_filenames):
            with Image.open(path) as image:
                width, height = image.size
            camera = (int(cameras.width[i]), int(cameras.height[i]))
            if (int(width * scale), int(height * scale)) != camera:  # the dataset resizes photos by `scale`
                bad.append((Path(path), (width, height), camera))
    if not bad:
        return
    path, (width, height), (cam_w, cam_h) = bad[0]
    if isinstance(parser_config, NerfstudioDataParserConfig):
        data = Path(parser_config.data)
        model = str(data if data.suffix == ".json" else data / "transforms.json")
    elif isinstance(parser_config, ColmapDataParserConfig):
        model = f"the COLMAP model ({Path(parser_config.data) / parser_config.colmap_path})"
    else:
        model = "the dataparser's cameras"
    if _RESOLUTION_FOLDER.match(path.parent.name):
        fix = downscaled_fix(path, (cam_w, cam_h), model)
    else:
        fix = f"replace it with the {cam_w}x{cam_h} photo its camera was made from, or remove it from {model}"
    more = f" ({len(bad) - 1} more photos differ from their cameras too)" if len(bad) > 1 else ""
    raise SceneDataError(f"{path} is {width}x{height} but its camera says {cam_w}x{cam_h}{more}; {fix}")


def downscaled_fix(path: Path, camera: Tuple[int, int], model: str) -> str:
    """The fix for a photo in `images_N/` that is not its camera's size: rewriting `images_N` helps only when the
    full-resolution photo it was written from is the right size; otherwise that photo is named."""
    factor = int(path.parent.name.rpartition("_")[2])
    source = path.parent.parent / "images" / path.name
    if not source.is_file():  # nothing can write images_N again: it holds the only copy of this photo
        return (f"there is no {source} to write it from, so {path.parent} holds the only copy: replace {path.name} with the "
                f"{camera[0]}x{camera[1]} photo its camera was made from, or remove it from {model}")
    try:
        with Image.open(source) as image:
            width, height = image.size
    except (OSError, ValueError):
        return f"delete {path.parent} to have it rewritten from {source.parent}"
    if any((fn(width / factor), fn(height / factor)) == tuple(camera) for fn in ROUNDING.values()):
        return f"delete {path.parent} to have it rewritten from {source.parent}"
    return (f"it is written from {source}, which is {width}x{height}, not {factor}x the camera's size: replace {source} "
            f"with the photo its camera was made from (then delete {path.parent}), or remove it from {model}")


@dataclass
class HpgsNerfstudioDataParserConfig(NerfstudioDataParserConfig):
    """nerfstudio-data (`transforms.json`) with the capture's seed points loaded as splatfacto's parser does."""

    _target: Type = field(default_factory=lambda: HpgsNerfstudio)
    load_3D_points: bool = True
    """Start the splat from the capture's points (`ply_file_path` in transforms.json, or sparse_pc.ply)."""

    def __post_init__(self) -> None:
        check_parser_values(self, "nerfstudio-data")


class HpgsNerfstudio(Nerfstudio):
    """nerfstudio's `Nerfstudio` parser; the seed points come from `plyfile` and no question is asked."""

    config: HpgsNerfstudioDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train"):
        data = Path(self.config.data)
        meta_path = data if data.suffix == ".json" else data / "transforms.json"
        if data.is_file() and data.suffix != ".json":
            raise SceneDataError(f"--data {data} is a file, not a capture folder; pass the folder holding transforms.json "
                                 "(or the transforms.json itself)")
        if not meta_path.is_file():
            raise SceneDataError(f"{meta_path} not found; pass --data to a folder made by ns-process-data (or a transforms.json)")
        frames = read_transforms_frames(meta_path)
        factor = self.config.downscale_factor
        paths = [meta_path.parent / f["file_path"] for f in frames]
        # nerfstudio reads images_N/<file name> with a factor N (written below from images/ if missing)
        missing = [p for p in paths if not p.exists()
                   and not (factor is not None and factor > 1 and (meta_path.parent / f"images_{factor}" / p.name).exists())]
        if missing:
            raise SceneDataError(f"{len(missing)} images named in {meta_path} are missing, e.g. {missing[0]}; restore them "
                                 f"or remove their frames from {meta_path.name}")
        if factor is not None and factor > 1:
            # nerfstudio reads images_N/<file name> and asks nothing: write it as mipnerf360 does (its rounding: floor)
            source = meta_path.parent / "images"
            if all(p.parent == source for p in paths):
                _make_downscaled_folder(source, paths, factor, "floor", model=str(meta_path))
        load_points, self.config.load_3D_points = self.config.load_3D_points, False  # the stock loader needs open3d
        try:
            outputs = super()._generate_dataparser_outputs(split)
            ply = None
            if load_points:
                meta = json.loads(meta_path.read_text())
                ply = meta_path.parent / meta.get("ply_file_path", "sparse_pc.ply")
        except UserError:
            raise
        except (KeyError, IndexError, TypeError, ValueError, AttributeError, AssertionError) as err:
            # a field of the wrong type or shape (a matrix that is not 4x4, a size that is not a number, ...)
            detail = str(err).splitlines()[0][:120] if str(err) else "no detail"
            raise SceneDataError(f"{meta_path} has a field nerfstudio cannot use ({type(err).__name__}: {detail}); "
                                 "restore it from the capture or re-run ns-process-data") from err
        finally:
            self.config.load_3D_points = load_points
        if ply is not None:
            points = read_ply_points(ply) if ply.is_file() else None
            if points is not None:  # none: the datamanager says what the splat starts from (`seed-points`)
                xyz, rgb = points
                transform = outputs.dataparser_transform.float()
                xyz = torch.cat([xyz, torch.ones_like(xyz[:, :1])], -1) @ transform.T * outputs.dataparser_scale
                outputs.metadata.update({"points3D_xyz": xyz, "points3D_rgb": rgb})
        return outputs


def read_transforms_frames(meta_path: Path) -> List[dict]:
    """The frames of a transforms.json; a one-line error for a file that is not valid JSON or has no frames."""
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:  # json.JSONDecodeError is a ValueError
        raise SceneDataError(f"{meta_path} is not readable JSON ({err}); restore it from the capture or re-run "
                             "ns-process-data") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames or not all(isinstance(f, dict) and isinstance(f.get("file_path"), str)
                                                             for f in frames):
        raise SceneDataError(f"{meta_path} has no \"frames\" list of {{\"file_path\": ...}} entries; restore it from the "
                             "capture or re-run ns-process-data")
    return frames


def read_ply_points(path: Path) -> Optional[Tuple[torch.Tensor, torch.Tensor]]:
    """(xyz float32 [N, 3], rgb uint8 [N, 3]) of a point cloud PLY (colours grey if it has none); None if empty."""
    from plyfile import PlyData

    try:
        vertex = PlyData.read(str(path))["vertex"].data
    except Exception as err:  # plyfile raises several types for damaged files
        raise SceneDataError(f"cannot read seed points {path} ({err}); fix or delete the file") from err
    if len(vertex) == 0:
        return None
    xyz = np.stack([vertex[k] for k in ("x", "y", "z")], -1).astype(np.float32)
    names = vertex.dtype.names or ()
    keys = next((k for k in (("red", "green", "blue"), ("r", "g", "b")) if all(c in names for c in k)), None)
    if keys is None:
        rgb = np.full_like(xyz, 128, dtype=np.uint8)
    else:
        rgb = np.stack([vertex[k] for k in keys], -1)
        rgb = (rgb * 255 + 0.5 if rgb.dtype.kind == "f" else rgb).clip(0, 255).astype(np.uint8)
    return torch.from_numpy(xyz), torch.from_numpy(rgb)


# ---- the choice of dataparser ---------------------------------------------------------------------------------

# `mipnerf360` first (the default); nerfstudio's own and its plugins' parsers after it, nerfstudio-data replaced.
DATAPARSERS = {
    "mipnerf360": MipNerf360DataParserConfig(),
    "nerfstudio-data": HpgsNerfstudioDataParserConfig(),
    **{name: config for name, config in all_dataparsers.items() if name != "nerfstudio-data"},
}
DataParserUnion = tyro.conf.OmitSubcommandPrefixes[  # type: ignore[valid-type]
    tyro.extras.subcommand_type_from_defaults(DATAPARSERS, prefix_names=False)
]
"""The dataparser subcommand of `ns-train hpgs` (options after it: `mipnerf360 --downscale-factor 2`)."""


def scene_dataparser(scene: Path) -> str:
    """The subcommand that reads the scene folder `scene`: `mipnerf360` (COLMAP model in sparse/0) or
    `nerfstudio-data` (transforms.json). One-line error for anything else."""
    scene = Path(scene)
    if (scene / "sparse" / "0").is_dir():
        return "mipnerf360"
    if (scene / "transforms.json").is_file():
        return "nerfstudio-data"
    raise SceneDataError(f"{scene} is not a scene folder (no sparse/0 COLMAP model, no transforms.json); pass a scene folder")


_RESOLUTION_FOLDER = re.compile(r"^images_(\d+)$")


def _shrunk_by(size: Tuple[int, int], camera: Tuple[int, int]) -> Optional[int]:
    """N > 1 when a photo of `size` is its `camera`'s size divided by N (any of nerfstudio's roundings)."""
    for n in range(2, 65):
        if any((fn(camera[0] / n), fn(camera[1] / n)) == tuple(size) for fn in ROUNDING.values()):
            return n
    return None


def view_name(image_path: Path, data_root: Path) -> str:
    """How a view is named everywhere (logs, checkpoints, results): its image's path relative to the data root,
    with a downscaled folder written as the full-resolution one (`images_2/0001.png` -> `images/0001.png`), so a
    photo keeps its name at every resolution. Blender's train and test splits both hold `r_0.png`: their names
    are `train/r_0.png` and `test/r_0.png`."""
    rel = Path(os.path.relpath(image_path, data_root))
    parts = rel.parts
    if len(parts) > 1 and _RESOLUTION_FOLDER.match(parts[0]):
        rel = Path("images", *parts[1:])
    return rel.as_posix()
