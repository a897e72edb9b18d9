"""Preference-pair CSVs in the HP-GS format, images, and image-disjoint splits.

CSV columns: `Image_1,Image_2,Human Preference[,Skipped]`. Image names are relative to the CSV's folder.
`Human Preference` 1 = Image_1 is the worse (more poorly reconstructed) render, 0 = Image_2 is, empty = not
labelled yet. `Skipped` 1 = the labeller skipped the pair. Only labelled, unskipped pairs train or score.
"""

from __future__ import annotations

import contextlib
import csv
import os
import random
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator, List, Optional, Sequence, Set, Tuple

import numpy as np

from hpgs_ns.errors import UserError

if TYPE_CHECKING:  # imported in load_image: `hpgs label --help` and `hpgs eval-pref --help` import this module
    import torch

COLUMNS = ("Image_1", "Image_2", "Human Preference")
SKIPPED = "Skipped"


class PairsError(UserError, ValueError):
    """A pairs CSV or one of its images is unusable; the one-line message names the file and the fix."""


@dataclass(frozen=True)
class Pair:
    """One row of a pairs CSV, with image paths resolved against the CSV's folder."""

    image_1: Path
    image_2: Path
    label: Optional[int]
    """1 = image_1 is worse, 0 = image_2 is worse, None = unlabelled."""
    skipped: bool = False

    @property
    def usable(self) -> bool:
        """Labelled and not skipped: the pairs that train and score."""
        return self.label is not None and not self.skipped


def parse_flag(value: Optional[str], csv_path: Path, line: int, column: str) -> Optional[int]:
    """A 0/1/empty cell -> 0, 1 or None; PairsError naming the file and line otherwise."""
    value = (value or "").strip()
    if value == "":
        return None
    try:
        number = float(value)
    except ValueError:
        number = None
    if number not in (0.0, 1.0):
        raise PairsError(f"{csv_path}:{line}: {column} must be 1, 0 or empty, got {value!r}; fix that row")
    return int(number)


def _image_path(csv_path: Path, name: str) -> Path:
    """An image name from a CSV as an absolute, normalised path (symlinks kept), so the same file named from
    two CSVs is one image for the image-disjoint split."""
    return Path(os.path.normpath(os.path.abspath(csv_path.parent / name)))


@contextlib.contextmanager
def csv_errors(csv_path: Path) -> Iterator[None]:
    """A CSV that is not UTF-8 text (Latin-1, a binary file) or that the csv module cannot split: PairsError."""
    try:
        yield
    except UnicodeDecodeError as err:
        raise PairsError(f"{csv_path}: not UTF-8 text (byte {err.object[err.start]:#04x} at offset {err.start}); save it "
                         "as UTF-8 CSV (or rewrite it with `hpgs collect`)") from None
    except csv.Error as err:
        raise PairsError(f"{csv_path}: not a readable CSV ({err}); fix the file or rewrite it with `hpgs collect`") from None


def pairs_reader(f, csv_path: Path) -> csv.DictReader:
    """A DictReader over an open pairs CSV with its header stripped and checked (PairsError if a column is
    missing)."""
    reader = csv.DictReader(f)
    header = [h.strip() for h in (reader.fieldnames or [])]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise PairsError(f"{csv_path}: missing column(s) {', '.join(missing)}; the header must be "
                         f"{','.join(COLUMNS)}[,{SKIPPED}]")
    reader.fieldnames = header
    return reader


def read_pairs(csv_path: Path) -> List[Pair]:
    """Every row of a pairs CSV (labelled or not); PairsError on a malformed file."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise PairsError(f"{csv_path}: pairs CSV not found; pass an existing file (columns {','.join(COLUMNS)})")
    with csv_errors(csv_path), open(csv_path, newline="", encoding="utf-8-sig") as f:
        reader = pairs_reader(f, csv_path)
        pairs = []
        for line, row in enumerate(reader, start=2):
            if None in row:  # more cells than header fields
                raise PairsError(f"{csv_path}:{line}: too many cells; fix that row to match the header")
            names = [(row.get(c) or "").strip() for c in COLUMNS[:2]]
            if not all(names):
                raise PairsError(f"{csv_path}:{line}: empty image name; every row needs Image_1 and Image_2")
            label = parse_flag(row.get(COLUMNS[2]), csv_path, line, COLUMNS[2])
            skipped = parse_flag(row.get(SKIPPED), csv_path, line, SKIPPED) == 1
            pairs.append(Pair(_image_path(csv_path, names[0]), _image_path(csv_path, names[1]), label, skipped))
    return pairs


def require_pairs(csv_paths: Sequence[Path]) -> None:
    """PairsError when no `--pairs` was given (tyro lets a repeatable option be left out): `hpgs train-pref` and
    `hpgs eval-pref` say it alike."""
    if not csv_paths:
        raise PairsError("--pairs is required: pass --pairs PAIRS.csv (written by `hpgs label DIR`); repeat it for "
                         "several files")


def read_usable_pairs(csv_paths: Iterable[Path], check_images: bool = True) -> List[Pair]:
    """Labelled, unskipped pairs of all CSVs; PairsError if an image they name is missing."""
    pairs = [p for path in csv_paths for p in read_pairs(path) if p.usable]
    if check_images:
        for pair in pairs:
            for image in (pair.image_1, pair.image_2):
                if not image.is_file():
                    raise PairsError(f"{image}: image named in a pairs CSV is missing; names are relative to the "
                                     "CSV's folder: restore the file or remove its rows")
    return pairs


def load_image(path: Path) -> torch.Tensor:
    """An image file as [3, H, W] float in [0, 1]; PairsError if missing or unreadable."""
    import torch
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            array = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise PairsError(f"{path}: image not found; restore it or remove the pairs that name it") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, struct.error, Image.DecompressionBombError) as err:
        raise PairsError(f"{path}: not a readable image ({type(err).__name__}); replace it or remove its pairs") from None
    return torch.from_numpy(array).permute(2, 0, 1).contiguous()


def check_image(path: Path) -> None:
    """PairsError unless `path` is a whole, readable image (`image_files.image_problem`): cheaper than `load_image`,
    run on every labelled image before training."""
    from hpgs_ns.image_files import image_problem

    if not path.exists():
        raise PairsError(f"{path}: image not found; restore it or remove the pairs that name it")
    problem = image_problem(path)
    if problem is not None:
        why = problem.splitlines()[0][:80]
        raise PairsError(f"{path}: not a readable image ({why}); replace it or remove its pairs")


def images_of(pairs: Iterable[Pair]) -> List[Path]:
    """Distinct images of `pairs`, in first-seen order."""
    return list(dict.fromkeys(p for pair in pairs for p in (pair.image_1, pair.image_2)))


def pairs_within(pairs: Iterable[Pair], images: Set[Path]) -> List[Pair]:
    """Pairs whose two images are both in `images`."""
    return [p for p in pairs if p.image_1 in images and p.image_2 in images]


def image_folds(images: Sequence[Path], k: int, seed: int = 0) -> List[Set[Path]]:
    """Split images into k disjoint, near-equal random groups (every image in exactly one)."""
    order = list(images)
    random.Random(seed).shuffle(order)
    return [set(order[i::k]) for i in range(k)]


def image_disjoint_split(pairs: Sequence[Pair], test_fraction: float, seed: int = 0) -> Tuple[List[Pair], List[Pair]]:
    """(train, test) pairs with no image on both sides: a random `test_fraction` of the images is held out;
    test pairs have both images held out, train pairs neither; pairs straddling the two are dropped."""
    images = images_of(pairs)
    if test_fraction <= 0 or len(images) < 4:
        return list(pairs), []
    order = list(images)
    random.Random(seed).shuffle(order)
    n_test = min(len(images) - 2, max(2, round(test_fraction * len(images))))
    held_out = set(order[:n_test])
    train = pairs_within(pairs, set(order[n_test:]))
    return train, pairs_within(pairs, held_out)
