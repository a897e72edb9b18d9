"""`hpgs demo`: the main job on the embedded synthetic scene, with nothing to download.

Generates a small synthetic 360-degree scene (Mip-NeRF 360 layout), runs the real `ns-train hpgs` on it with a
schedule scaled to finish in minutes on a 2-core CPU (or the full protocol on a GPU), evaluates the test views
with `ns-eval`, and prints the test PSNR/SSIM/LPIPS and where the run lies.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import List, Literal, Optional

import torch
from rich.console import Console

from hpgs_ns.ns_train import ns_train_command

CONSOLE = Console(stderr=True)


@dataclass
class Demo:
    """Generate the synthetic scene, train `hpgs` on it, and print the test metrics."""

    out: Path = Path("outputs/demo")
    """Folder for the scene and the run."""
    selector: str = "hpgs"
    """Selector to use (see `ns-train hpgs --help`)."""
    layout: str = "ring"
    """Synthetic scene layout."""
    steps: Optional[int] = None
    """Training steps; default 800 on CPU (select every 100), 15000 on GPU (select every 2000)."""
    num_initial_views: int = 6
    """Views active at step 0."""
    seed: int = 0
    """Seed for the scene, the initial views and the selector."""
    rasterizer: Literal["auto", "gsplat", "cpu"] = "auto"
    """Rasterizer (auto: gsplat when CUDA is available)."""

    def main(self) -> None:
        from hpgs_ns.scenes.synthetic import make_scene

        scene = self.out / f"scene-{self.layout}-seed{self.seed}"
        if not (scene / "sparse" / "0").exists():
            CONSOLE.print(f"[bold]Generating the synthetic scene[/bold] -> {scene}")
            make_scene(scene, layout=self.layout, seed=self.seed)
        gpu = torch.cuda.is_available() and self.rasterizer != "cpu"
        steps = self.steps or (15000 if gpu else 800)
        every = max(steps // 8, 1) if self.steps or not gpu else 2000
        run_name = f"{self.selector}-seed{self.seed}"
        cmd = train_command(scene, self.out, run_name, self.selector, steps, every, self.num_initial_views, self.seed, self.rasterizer)
        CONSOLE.print(f"[bold]Training[/bold]: {shlex.join(cmd)}")
        start = time.perf_counter()
        subprocess.run(cmd, check=True)
        minutes = (time.perf_counter() - start) / 60
        config = latest_config(self.out / "runs" / "hpgs" / run_name)
        metrics = evaluate(config)
        selected = json.loads((config.parent / "selected_views.json").read_text())
        print(
            f"test PSNR {metrics['psnr']:.2f} dB  SSIM {metrics['ssim']:.3f}  LPIPS {metrics['lpips']:.3f}  "
            f"({len(selected['active'])} views, {len(selected['rounds'])} added by {self.selector}, {minutes:.1f} min)"
        )
        print(f"run: {config.parent}")
        print(f"inspect: ns-viewer --load-config {config}")


def train_command(
    scene: Path, out: Path, run_name: str, selector: str, steps: int, every: int, initial: int, seed: int, rasterizer: str
) -> List[str]:
    """The `ns-train hpgs` command line the demo runs (also printed, so users can adapt it): splatfacto's
    schedule shrunk to the step count."""
    return ns_train_command(
        scene, out, "runs", run_name, steps,
        datamanager={"num-initial-views": initial, "select-every": every, "selector": selector, "seed": seed},
        model={
            "rasterizer": rasterizer,
            "warmup-length": min(500, steps // 8),
            "refine-every": min(100, max(steps // 40, 10)),
            "resolution-schedule": min(3000, steps // 4),
            "sh-degree-interval": min(1000, steps // 6),
        },
    )


def latest_config(run_dir: Path) -> Path:
    configs = sorted(run_dir.rglob("config.yml"), key=lambda p: p.stat().st_mtime)
    if not configs:
        raise FileNotFoundError(f"no config.yml under {run_dir}; did ns-train fail?")
    return configs[-1]


def evaluate(config: Path) -> dict:
    """Run stock `ns-eval` on the run's checkpoint and return its mean test metrics."""
    out = config.parent / "eval.json"
    subprocess.run(
        [sys.executable, "-m", "nerfstudio.scripts.eval", "--load-config", str(config), "--output-path", str(out)],
        check=True,
    )
    return json.loads(out.read_text())["results"]
