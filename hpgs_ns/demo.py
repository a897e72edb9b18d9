"""`hpgs demo`: the main job on the embedded synthetic scene, with nothing to download.

Generates a small synthetic 360-degree scene (Mip-NeRF 360 layout), runs the real `ns-train hpgs` on it with a
schedule scaled to finish in minutes on a 2-core CPU (or the full protocol on a GPU), evaluates the test views
(`ns-eval`'s metrics, computed by the training process: `--final-eval-json`), and prints the test PSNR/SSIM/LPIPS and where the run lies.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import List, Literal, Optional

from rich.console import Console

from hpgs_ns.errors import UserError
from hpgs_ns.ns_train import ns_train_command

CONSOLE = Console(stderr=True)


@dataclass
class Demo:
    """Generate the synthetic scene, train `hpgs` on it, and print the test metrics."""

    out: Path = Path("outputs/demo")
    """Folder for the scene and the run."""
    selector: Optional[str] = None
    """Selector to use (see `ns-train hpgs --help`); default: `ns-train hpgs`'s."""
    layout: str = "ring"
    """Synthetic scene layout."""
    steps: Optional[int] = None
    """Training steps; default 300 on CPU (select every 100), 15000 on GPU (select every 2000)."""
    num_initial_views: int = 6
    """Views active at step 0."""
    num_cameras: int = 32
    """Cameras of the synthetic scene (every 8th is a test view; the rest are initial views or candidates)."""
    views_per_round: Optional[int] = None
    """Views each selection round adds; default 3 on CPU, 1 on GPU."""
    max_rounds: Optional[int] = None
    """Selection rounds; default 2 on CPU (6 views added), 7 on GPU."""
    seed: int = 0
    """Seed for the scene, the initial views and the selector."""
    rasterizer: Literal["auto", "gsplat", "cpu"] = "auto"
    """Rasterizer (auto: gsplat when CUDA is available)."""

    def main(self) -> None:
        import torch  # here, not at module level: `hpgs demo --help` does not need it

        from hpgs_ns.offline_weights import LPIPS_NETS, lpips_weights_path
        from hpgs_ns.scenes.synthetic import make_scene

        # Every run needs the LPIPS trunks (splatfacto's LPIPS metric, the shipped preference model): say what to
        # install now, in one line, rather than after the scene and ns-train's start-up.
        for net in LPIPS_NETS:
            lpips_weights_path(net)
        scene = self.out / f"scene-{self.layout}-{self.num_cameras}cams-seed{self.seed}"
        if not (scene / "sparse" / "0").exists():
            CONSOLE.print(f"[bold]Generating the synthetic scene[/bold] -> {scene}")
            make_scene(scene, layout=self.layout, num_cameras=self.num_cameras, seed=self.seed)
        gpu = torch.cuda.is_available() and self.rasterizer != "cpu"
        steps = self.steps or (15000 if gpu else 300)
        every = 2000 if gpu and not self.steps else (100 if not self.steps else max(steps // 8, 1))
        rounds = self.max_rounds if self.max_rounds is not None else (7 if gpu else 2)
        per_round = self.views_per_round or (1 if gpu else 3)
        run_name = f"{self.selector or 'default'}-seed{self.seed}"
        cmd = train_command(scene, self.out, run_name, self.selector, steps, every, self.num_initial_views, self.seed,
                            self.rasterizer, per_round, rounds)
        # On the CPU one intra-op thread: the pure-PyTorch rasterizer runs several times faster than with two on 2
        # cores (an OMP_NUM_THREADS already set wins).
        env = dict(os.environ) if gpu else {"OMP_NUM_THREADS": "1", **os.environ}
        CONSOLE.print(f"[bold]Training[/bold]: {shlex.join(cmd)}")
        start = time.perf_counter()
        if subprocess.run(cmd, env=env).returncode != 0:
            raise UserError("ns-train failed (its error is printed above); the command is printed before it")
        minutes = (time.perf_counter() - start) / 60
        config = latest_config(self.out / "runs" / "hpgs" / run_name)
        metrics = json.loads((config.parent / "final_eval.json").read_text())["results"]
        from hpgs_ns.selection.log import SelectionLog

        selected = SelectionLog.read(config.parent)
        print(
            f"test PSNR {metrics['psnr']:.2f} dB  SSIM {metrics['ssim']:.3f}  LPIPS {metrics['lpips']:.3f}  "
            f"({len(selected.active)} views, {len(selected.chosen)} added by {selected.selector} in {len(selected.rounds)} rounds, "
            f"{minutes:.1f} min)"
        )
        print(f"run: {config.parent}")
        print(f"inspect: ns-viewer --load-config {config}")


def train_command(
    scene: Path, out: Path, run_name: str, selector: Optional[str], steps: int, every: int, initial: int, seed: int,
    rasterizer: str, views_per_round: int = 1, max_rounds: int = 7,
) -> List[str]:
    """The `ns-train hpgs` command line the demo runs (also printed, so users can adapt it): splatfacto's
    schedule shrunk to the step count."""
    return ns_train_command(
        scene, out, "runs", run_name, steps,
        datamanager={"num-initial-views": initial, "seed": seed},
        selection={**({"selector": selector} if selector else {}), "select-every": every,
                   "views-per-round": views_per_round, "max-rounds": max_rounds},
        model={
            "rasterizer": rasterizer,
            "warmup-length": min(500, steps // 6),
            "refine-every": min(100, max(steps // 12, 10)),
            # Densify in the first half only, as splatfacto does (15000 of 30000): on 96x72 views a longer window
            # grows 4000 points into ~90k Gaussians, which the CPU rasterizer pays for at every step.
            "stop-split-at": min(15000, steps // 2),
            "resolution-schedule": min(3000, steps // 4),
            "sh-degree-interval": min(1000, steps // 6),
        },
        # ns-eval's metrics computed in the training process (hpgs_ns.trainer): ns-eval's own start-up is ~20 s.
        extra=["--final-eval-json", str(out / "runs" / "hpgs" / run_name / "final_eval.json")],
    )


def latest_config(run_dir: Path) -> Path:
    configs = sorted(run_dir.rglob("config.yml"), key=lambda p: p.stat().st_mtime)
    if not configs:
        raise FileNotFoundError(f"no config.yml under {run_dir}; did ns-train fail?")
    return configs[-1]
