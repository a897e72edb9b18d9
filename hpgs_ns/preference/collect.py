"""`hpgs collect`: make the renders a person labels to train a preference model (HP-GS Sec. 3.2).

Trains `hpgs` (splatfacto) on a few random training views with no view selection, and every `every` steps
renders every *training-split* camera (test views never: their photos must not leak into labels). Each render's
error against its photo goes into `renders.csv`; `pairs.csv` gets N random pairs, unlabelled, in the HP-GS
format (`Image_1,Image_2,Human Preference`), ready for `hpgs label`.
"""

from __future__ import annotations

import random
import shlex
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, List, Literal, Optional

import numpy as np
import yaml
from PIL import Image
from rich.console import Console
from rich.progress import track

from hpgs_ns.atomic_write import write_csv_atomic
from hpgs_ns.errors import UserError
from hpgs_ns.ns_train import ns_train_command

if TYPE_CHECKING:  # torch and nerfstudio are imported where used: `hpgs collect --help` imports this module
    import torch

CONSOLE = Console(stderr=True)


@dataclass
class Collect:
    """Train on a few random views and render every training camera periodically, for labelling."""

    data: Path
    """Scene folder: Mip-NeRF 360 layout (COLMAP in sparse/0) or nerfstudio-data (transforms.json)."""
    out: Path
    """Output folder: renders/, renders.csv, pairs.csv (and the training run under run/)."""
    num_views: int = 10
    """Random training views the splat is trained on."""
    steps: int = 15000
    """Training steps (HP-GS: 15000)."""
    every: int = 2000
    """Render all training cameras every this many steps (HP-GS: 2000)."""
    pairs: int = 500
    """Random pairs drawn into pairs.csv."""
    seed: int = 0
    """Seeds the views, the training and the pairs."""
    downscale_factor: Optional[int] = None
    """Image downscale factor for the dataparser (None: nerfstudio's automatic choice)."""
    rasterizer: Literal["auto", "gsplat", "cpu"] = "auto"
    """Rasterizer for training and rendering."""
    save_short_side: Optional[int] = None
    """Save the copied renders with this short side (JPEG, quality 95) instead of full-size PNG; metrics are
    always computed at full size. Keeps large collections small enough to move around."""
    extra_args: str = ""
    """Extra `ns-train hpgs` arguments (quoted), e.g. schedule options for short runs."""

    def main(self) -> None:
        from hpgs_ns.dataparser import scene_dataparser

        if not self.data.is_dir():
            raise UserError(f"hpgs collect: scene folder {self.data} does not exist; pass --data PATH")
        run_root = self.out / "run"
        datamanager = {
            "num-initial-views": self.num_views, "initial-views": "random", "max-rounds": 0, "seed": self.seed,
            "snapshot-every": self.every,
        }
        cmd = ns_train_command(
            self.data, run_root, "collect", f"seed{self.seed}", self.steps, datamanager=datamanager,
            model={"rasterizer": self.rasterizer}, extra=shlex.split(self.extra_args),
            dataparser=scene_dataparser(self.data),
            dataparser_options={} if self.downscale_factor is None else {"downscale-factor": self.downscale_factor},
        )
        run_dir = run_root / "collect" / "hpgs" / f"seed{self.seed}"
        final = run_dir / "snapshots" / f"step-{self.steps - self.steps % self.every:06d}"
        if not final.is_dir():  # not finished (or never started): train from scratch
            CONSOLE.print(f"[bold]Training[/bold]: {shlex.join(cmd)}")
            subprocess.run(cmd, check=True)
        rows = score_snapshots(run_dir, self.out / "renders", self.save_short_side)
        write_csv_atomic(self.out / "renders.csv", ["image", "step", "view", "psnr", "ssim", "lpips"], rows)
        pairs = draw_pairs([r["image"] for r in rows], self.pairs, self.seed)
        write_csv_atomic(self.out / "pairs.csv", ["Image_1", "Image_2", "Human Preference"], pairs)
        print(f"{len(rows)} renders, {len(pairs)} pairs -> {self.out}  (label with: hpgs label {self.out})")


def ground_truth_images(run_dir: Path) -> dict:
    """Training-split photo paths by file stem, at the resolution the run trained on (from its config.yml)."""
    config = yaml.load((run_dir / "config.yml").read_text(), Loader=yaml.Loader)
    parser = config.pipeline.datamanager.dataparser
    parser.data = config.pipeline.datamanager.data or parser.data
    outputs = parser.setup().get_dataparser_outputs(split="train")
    return {Path(p).stem: Path(p) for p in outputs.image_filenames}


def score_snapshots(run_dir: Path, render_dir: Path, save_short_side: Optional[int] = None) -> List[dict]:
    """Copy every snapshot render to `render_dir` and measure it against its photo."""
    import torch

    from hpgs_ns.metrics import lpips, psnr, ssim

    photos = ground_truth_images(run_dir)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    render_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    files = sorted((run_dir / "snapshots").glob("step-*/*.png"))
    for path in track(files, description="scoring renders", console=CONSOLE):
        step = int(path.parent.name.split("-")[1])
        render = load_rgb(path).to(device)
        photo = load_rgb(photos[path.stem], size=(render.shape[1], render.shape[0])).to(device)
        name = f"s{step:06d}_{path.stem}." + ("jpg" if save_short_side else "png")
        if save_short_side:
            with Image.open(path) as im:
                scale = save_short_side / min(im.size)
                im.convert("RGB").resize((round(im.width * scale), round(im.height * scale)), Image.Resampling.BICUBIC).save(
                    render_dir / name, quality=95
                )
        else:
            shutil.copyfile(path, render_dir / name)
        rows.append(
            {"image": f"renders/{name}", "step": step, "view": path.stem, "psnr": f"{psnr(render, photo):.4f}",
             "ssim": f"{ssim(render, photo):.5f}", "lpips": f"{lpips(render, photo):.5f}"}
        )
    return rows


def load_rgb(path: Path, size: Optional[tuple] = None) -> torch.Tensor:
    """[H, W, 3] float in [0, 1]; resized to `size` (W, H) if given."""
    import torch

    with Image.open(path) as im:
        im = im.convert("RGB")
        if size is not None and im.size != tuple(size):
            im = im.resize(size, Image.Resampling.BICUBIC)
        return torch.from_numpy(np.asarray(im, dtype=np.float32) / 255.0)


def draw_pairs(images: List[str], n: int, seed: int) -> List[dict]:
    """n distinct random unordered pairs (fewer if there are not that many), unlabelled."""
    rng = random.Random(seed)
    total = len(images) * (len(images) - 1) // 2
    seen, out = set(), []
    while len(out) < min(n, total):
        a, b = rng.sample(range(len(images)), 2)
        if (min(a, b), max(a, b)) in seen:
            continue
        seen.add((min(a, b), max(a, b)))
        out.append({"Image_1": images[a], "Image_2": images[b], "Human Preference": ""})
    return out

