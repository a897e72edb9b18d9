"""Stress mode for `hpgs bench`: perturbed copies of a scene (`bench.report` tabulates how much each selector loses).

Each perturbation writes a copy of a Mip-NeRF 360 scene folder (`images/`, `images_N/`, `sparse/0/`) named
`<scene>+<perturbation>`, and touches the *training* views only: the test split (every 8th image in file-name
order) keeps its exact images and poses, so clean and perturbed runs are scored on the same test set.

- `pose-noise`: seeded Gaussian rotation and camera-centre noise on the COLMAP poses (a miscalibrated SfM);
- `exposure`: seeded per-image gain and gamma (auto-exposure, changing light);
- `corrupt`: a few image files truncated or emptied (a bad copy); the dataparser drops them with a warning.

Copies are built in a temp folder and renamed into place; a copy whose `stress.json` records the same source
and strengths is reused. Image files a perturbation does not change are hard links to the source's.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import List, Literal, Optional, Sequence, Tuple

import numpy as np
from rich.console import Console

from hpgs_ns.atomic_write import atomic_path, write_json_atomic
from hpgs_ns.errors import UserError

CONSOLE = Console(stderr=True)
STRESS_FILE = "stress.json"
EVAL_INTERVAL = 8  # the dataparser's Mip-NeRF 360 rule: every 8th image in file-name order is a test view

PerturbationName = Literal["pose-noise", "exposure", "corrupt"]


class StressError(UserError, ValueError):
    """A scene cannot be perturbed (not a scene folder, too few training views)."""


@dataclass
class PoseNoise:
    """Gaussian noise on the training views' COLMAP poses: each camera turns about a random axis and its centre
    moves; 3D points and 2D keypoints stay, as after a bundle adjustment that did not converge."""

    translation: float = 0.02
    """RMS camera-centre displacement, as a fraction of the cameras' RMS distance from their mean centre."""
    rotation_deg: float = 1.0
    """RMS rotation angle in degrees."""

    def apply(self, scene: Path, train: Sequence[str], rng: np.random.Generator) -> dict:
        from nerfstudio.data.utils.colmap_parsing_utils import rotmat2qvec

        from hpgs_ns.scenes.colmap_model import camera_pose, read_images, write_images

        model = scene / "sparse" / "0"
        images = read_images(model)
        by_name = {im.name: im for im in images.values()}
        poses = {name: camera_pose(im) for name, im in by_name.items()}
        centres = np.stack([centre for _, centre in poses.values()])
        spread = float(np.sqrt(((centres - centres.mean(0)) ** 2).sum(1).mean()))
        # Per-axis sigma of 1/sqrt(3) of the target makes the RMS of the 3D vector equal the target.
        sigma_t = self.translation * spread / math.sqrt(3)
        sigma_r = math.radians(self.rotation_deg) / math.sqrt(3)
        moved = {}
        for name in sorted(train):
            im = by_name[name]
            axis_angle = rng.normal(0.0, sigma_r, 3)
            shift = rng.normal(0.0, sigma_t, 3)
            # World-from-camera rotation turned by `noise` (in the world frame), centre shifted.
            rotation, centre = poses[name]
            new_rotation = rotation @ rodrigues(axis_angle).T
            new_centre = centre + shift
            images[im.id] = im._replace(qvec=rotmat2qvec(new_rotation), tvec=-new_rotation @ new_centre)
            moved[name] = {"rotation_deg": math.degrees(float(np.linalg.norm(axis_angle))), "translation": float(np.linalg.norm(shift))}
        write_images(model, images)
        rms = lambda key: math.sqrt(sum(m[key] ** 2 for m in moved.values()) / max(len(moved), 1))  # noqa: E731
        return {"camera_spread": spread, "rms_rotation_deg": rms("rotation_deg"), "rms_translation": rms("translation"), "views": moved}


@dataclass
class Exposure:
    """Per-image exposure changes on the training views: `out = gain * in ** gamma` on [0, 1] colours, with a
    seeded gain and gamma per image (every resolution of an image gets the same pair)."""

    gain: Tuple[float, float] = (0.6, 1.4)
    """Range of the uniform random gain."""
    gamma: Tuple[float, float] = (0.8, 1.25)
    """Range of the gamma (log-uniform, so 0.8 and 1.25 are equally likely)."""

    def apply(self, scene: Path, train: Sequence[str], rng: np.random.Generator) -> dict:
        from PIL import Image

        changed = {}
        for name in sorted(train):
            gain = float(rng.uniform(*self.gain))
            gamma = float(math.exp(rng.uniform(math.log(self.gamma[0]), math.log(self.gamma[1]))))
            changed[name] = {"gain": gain, "gamma": gamma}
            lut = np.clip(np.round(255 * gain * (np.arange(256) / 255) ** gamma), 0, 255).astype(np.uint8)
            for path in _image_copies(scene, name):
                with Image.open(path) as image:
                    fmt, mode = image.format, image.mode
                    pixels = np.asarray(image.convert("RGBA" if "A" in mode else "RGB")).copy()
                pixels[..., :3] = lut[pixels[..., :3]]  # alpha untouched
                _replace_file(path, lambda tmp, pixels=pixels, fmt=fmt: Image.fromarray(pixels).save(tmp, format=fmt, quality=95))
        return {"views": changed}


@dataclass
class Corrupt:
    """A few training images made unreadable (truncated to a fraction of their bytes, or emptied), in every
    resolution folder: what a bad copy or a full disk leaves behind."""

    count: int = 3
    """Number of training images to corrupt."""
    keep_fraction: float = 0.4
    """Truncated files keep this fraction of their bytes (every other corrupted file is emptied instead)."""

    def apply(self, scene: Path, train: Sequence[str], rng: np.random.Generator) -> dict:
        if not 0 < self.count < len(train):
            raise StressError(f"corrupt count {self.count} must be between 1 and {len(train) - 1} (the training views)")
        chosen = sorted(rng.choice(sorted(train), size=self.count, replace=False).tolist())
        kinds = {}
        for k, name in enumerate(chosen):
            kinds[name] = "truncated" if k % 2 == 0 else "empty"
            for path in _image_copies(scene, name):
                data = path.read_bytes()
                cut = data[: int(len(data) * self.keep_fraction)] if kinds[name] == "truncated" else b""
                _replace_file(path, lambda tmp, cut=cut: Path(tmp).write_bytes(cut))
        return {"views": kinds}


@dataclass
class StressConfig:
    """Strengths of the `hpgs bench --stress` perturbations."""

    seed: int = 0
    """Seed for every perturbation's random draws."""
    pose_noise: PoseNoise = field(default_factory=PoseNoise)
    exposure: Exposure = field(default_factory=Exposure)
    corrupt: Corrupt = field(default_factory=Corrupt)

    def perturbation(self, name: str):
        table = {"pose-noise": self.pose_noise, "exposure": self.exposure, "corrupt": self.corrupt}
        if name not in table:
            raise StressError(f"unknown perturbation {name!r}; choose from {', '.join(table)}")
        return table[name]


def rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] of a rotation vector [3] (axis times angle in radians)."""
    angle = float(np.linalg.norm(axis_angle))
    if angle < 1e-12:
        return np.eye(3)
    k = axis_angle / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def split_names(scene: Path) -> Tuple[List[str], List[str]]:
    """(training, test) image names of a scene: the COLMAP model's images in file-name order, every 8th a test
    view, as the dataparser splits them."""
    from hpgs_ns.scenes.colmap_model import read_images

    images = read_images(scene / "sparse" / "0")
    if images is None:
        raise StressError(f"{scene} is not a scene folder (no sparse/0/images.bin or .txt); pass a Mip-NeRF 360 style scene")
    names = sorted(Path(im.name).name for im in images.values())
    return [n for i, n in enumerate(names) if i % EVAL_INTERVAL != 0], [n for i, n in enumerate(names) if i % EVAL_INTERVAL == 0]


def perturbed_copy(scene: Path, name: str, out_dir: Path, config: Optional[StressConfig] = None) -> Path:
    """`out_dir/<scene>+<name>`: the scene with perturbation `name` applied to its training views. Reused when it
    exists with the same source and strengths; rebuilt (temp folder, then rename) otherwise."""
    config = config or StressConfig()
    scene = Path(scene).resolve()
    perturbation = config.perturbation(name)
    if not (scene / "sparse" / "0").is_dir():
        raise StressError(f"{scene} is not a scene folder (no sparse/0); pass a Mip-NeRF 360 style scene")
    target = Path(out_dir) / f"{scene.name}+{name}"
    params = {"source": str(scene), "perturbation": name, "seed": config.seed, "strength": asdict(perturbation)}
    params = json.loads(json.dumps(params))  # tuples as lists, as read back from stress.json
    if target.is_dir():
        try:
            if json.loads((target / STRESS_FILE).read_text())["params"] == params:
                return target
        except (OSError, ValueError, KeyError):
            pass
        CONSOLE.print(f"[yellow]{target} was made from another source or strength; rebuilding it")
    train, _ = split_names(scene)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=target.parent))
    try:
        _copy_scene(scene, tmp / "scene")
        # One stream per perturbation, so adding a perturbation never changes another's draws.
        rng = np.random.default_rng([config.seed, zlib.crc32(name.encode())])
        report = perturbation.apply(tmp / "scene", train, rng)
        write_json_atomic(tmp / "scene" / STRESS_FILE, {"params": params, "report": report}, indent=1)
        if target.exists():
            os.rename(target, tmp / "old")
        os.rename(tmp / "scene", target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def _copy_scene(source: Path, dest: Path) -> None:
    """Copy a scene folder; image files are hard-linked (perturbations replace files, never write into them),
    everything else is copied."""
    for root, _, files in os.walk(source):
        rel = Path(root).relative_to(source)
        (dest / rel).mkdir(parents=True, exist_ok=True)
        linkable = rel.parts and rel.parts[0].startswith("images")
        for f in files:
            src, dst = Path(root) / f, dest / rel / f
            if linkable:
                try:
                    os.link(src, dst)
                    continue
                except OSError:  # another filesystem
                    pass
            shutil.copy2(src, dst)
    os.chmod(dest, 0o755)


def _image_copies(scene: Path, name: str) -> List[Path]:
    """Every resolution of image `name`: `images/name`, `images_2/name`, ... that exist."""
    return sorted(p / name for p in scene.iterdir() if p.is_dir() and p.name.startswith("images") and (p / name).is_file())


def _replace_file(path: Path, write) -> None:
    """Write a new file beside `path` with `write(tmp_path)`, then rename it over `path` (which may be a hard link
    to the source scene's file: renaming over it leaves the source alone)."""
    with atomic_path(path, suffix=path.suffix) as tmp:
        write(str(tmp))
