"""`hpgs bench`: run time against error for every selector, through the real `ns-train hpgs` pipeline.

One run per (scene, protocol, selector, seed), plus two reference rows per (scene, protocol, seed):
`initial` (no views added) and `all` (every training view). Each run writes
`OUT/<scene>/<protocol>/<selector>/seed<k>.json`; runs whose JSON exists are skipped, so a killed sweep resumes.
`hpgs bench --report-only` rebuilds the markdown table and the plots from whatever JSON is there.
`hpgs bench --stress pose-noise exposure corrupt` also runs every scene perturbed (`hpgs_ns/stress.py`): copies
`OUT/_scenes/<scene>+<perturbation>`, results under `OUT/<scene>+<perturbation>/`, and `stress.md` beside `table.md`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple

import tyro
from rich.console import Console

from hpgs_ns.atomic_write import write_text_atomic
from hpgs_ns.executors import ExecutorConfig, run_sweep
from hpgs_ns.stress import PerturbationName, StressConfig, StressError, stress_plot, stress_table, stressed_scenes

CONSOLE = Console(stderr=True)
SELECTORS = ("random", "farthest", "fisher", "hpgs", "condorcet")
REFERENCES = ("initial", "all")


@dataclass(frozen=True)
class Protocol:
    """How many views to start from and when to add more."""

    name: str
    steps: int
    initial_views: int
    initial_mode: str
    select_every: int = 0
    select_at: Tuple[int, ...] = ()
    max_rounds: int = 7


def fisherrf_schedule(initial: int = 4, final: int = 20, per_view: int = 100) -> Tuple[int, ...]:
    """FisherRF adds a view every |train| x 100 steps: 400, 900, 1500, ... up to `final` views."""
    steps, t = [], 0
    for n in range(initial, final):
        t += n * per_view
        steps.append(t)
    return tuple(steps)


PROTOCOLS = {
    "hpgs": Protocol("hpgs", steps=15000, initial_views=20, initial_mode="even", select_every=2000, max_rounds=7),
    "fisherrf": Protocol(
        "fisherrf", steps=20000, initial_views=4, initial_mode="fps", select_at=fisherrf_schedule(), max_rounds=16
    ),
}


def scaled(protocol: Protocol, scale: float) -> Protocol:
    """The protocol with every step count multiplied by `scale` (short CPU runs keep the same shape)."""
    if scale == 1.0:
        return protocol
    return Protocol(
        protocol.name,
        steps=max(int(protocol.steps * scale), 1),
        initial_views=protocol.initial_views,
        initial_mode=protocol.initial_mode,
        select_every=max(int(protocol.select_every * scale), 1) if protocol.select_every else 0,
        select_at=tuple(max(int(s * scale), 1) for s in protocol.select_at),
        max_rounds=protocol.max_rounds,
    )


@dataclass
class Bench:
    """Benchmark selectors (test PSNR/SSIM/LPIPS, wall and selection time, memory) on scenes."""

    scenes: List[Path] = field(default_factory=list)
    """Scene folders (Mip-NeRF 360 layout), or `synthetic:ring`, `synthetic:occluded`, `synthetic:sparse-objects`
    for the embedded procedural scenes (generated into OUT/_scenes on first use)."""
    out: Path = Path("benchmarks/results/bench")
    """Results folder (one JSON per run; table and plots beside)."""
    selectors: List[str] = field(default_factory=lambda: list(SELECTORS))
    """Selectors to run."""
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])
    """Seeds: initial random views, selector randomness and torch."""
    protocols: List[Literal["hpgs", "fisherrf"]] = field(default_factory=lambda: ["hpgs"])
    """View-addition protocols."""
    references: bool = True
    """Also run the `initial` (no additions) and `all` (every training view) rows."""
    step_scale: float = 1.0
    """Multiply every step count (e.g. 0.01 for a CPU smoke run)."""
    initial_views: Optional[int] = None
    """Override the protocol's number of initial views (small scenes)."""
    max_runs: Optional[int] = None
    """Stop after this many new runs (fit a sweep into a time budget; re-run to continue)."""
    downscale_factor: Optional[int] = None
    """Dataparser downscale factor (e.g. 2 for the shared bonsai-device images_2)."""
    rasterizer: Literal["auto", "gsplat", "cpu"] = "auto"
    """Rasterizer for all runs."""
    reset_after_add: bool = False
    """Reset the model and its schedules after each added view (FisherRF); results go under `<protocol>-reset`."""
    strict_init: bool = False
    """Start from seed points seen by two initial views only (needs COLMAP tracks); results go under `<protocol>-strict`."""
    extra_args: str = ""
    """Extra `ns-train hpgs` arguments for every run (quoted). A finished run made with other arguments is an
    error on resume, not skipped: pass another `--out`."""
    report_only: bool = False
    """Only rebuild the table and plots from existing JSON."""
    stress: List[PerturbationName] = field(default_factory=list)
    """Also run every scene under these perturbations of its training views (copies in OUT/_scenes)."""
    stress_config: StressConfig = field(default_factory=StressConfig)
    """Strength and seed of each perturbation."""
    cluster: tyro.conf.OmitArgPrefixes[ExecutorConfig] = field(default_factory=ExecutorConfig)
    """Where the runs execute (`--executor local|ray|slurm` and its options)."""

    def main(self) -> None:
        if not self.report_only:
            self.scenes = resolve_scenes(self.scenes, self.out / "_scenes")
        if self.stress and not self.report_only:
            try:
                self.scenes = stressed_scenes(self.scenes, self.stress, self.out / "_scenes", self.stress_config)
            except StressError as err:
                raise SystemExit(f"hpgs bench: {err}") from None
        if not self.report_only:
            self.run_all()
        rows = load_results(self.out)
        if not rows:
            raise SystemExit(f"hpgs bench: no results under {self.out}")
        table = markdown_table(rows)
        write_text_atomic(self.out / "table.md", table)
        print(table)
        work = work_table(rows)
        if work:
            write_text_atomic(self.out / "work.md", work)
            print(work)
        stress = stress_table(rows)
        if stress:
            write_text_atomic(self.out / "stress.md", stress)
            print(stress)
            for path in stress_plot(rows, self.out):
                CONSOLE.print(f"plot: {path}")
        for path in make_plots(rows, self.out):
            CONSOLE.print(f"plot: {path}")

    def jobs(self) -> List[Tuple[Path, Protocol, str, int]]:
        jobs = []
        for scene in self.scenes:
            for pname in self.protocols:
                protocol = scaled(PROTOCOLS[pname], self.step_scale)
                if self.reset_after_add:
                    protocol = dataclasses.replace(protocol, name=f"{protocol.name}-reset")
                if self.strict_init:
                    protocol = dataclasses.replace(protocol, name=f"{protocol.name}-strict")
                for seed in self.seeds:
                    names = list(self.selectors) + (list(REFERENCES) if self.references else [])
                    for name in names:
                        jobs.append((scene, protocol, name, seed))
        return jobs

    def run_all(self) -> None:
        for scene in self.scenes:
            if not (scene / "sparse" / "0").is_dir():
                raise SystemExit(f"hpgs bench: {scene} is not a scene folder (no sparse/0); pass --scenes PATH")
        todo = []
        for job in self.jobs():
            path = result_path(self.out, job[0], job[1].name, job[2], job[3])
            if not path.exists():
                todo.append(job)
                continue
            made_with = json.loads(path.read_text()).get("settings")  # absent in results older than this check
            settings = run_settings(self, job[1])
            if made_with is not None and made_with != settings:
                changed = ", ".join(k for k in made_with if made_with[k] != settings.get(k))
                raise SystemExit(
                    f"hpgs bench: {path} was made with other settings ({changed}); pass another --out to keep both, "
                    "or delete it to re-run"
                )
        if self.max_runs is not None and len(todo) > self.max_runs:
            CONSOLE.print(f"[yellow]--max-runs {self.max_runs}: {len(todo) - self.max_runs} runs left; run again to continue")
            todo = todo[: self.max_runs]
        run_sweep(self, todo, self.cluster)


SYNTHETIC = "synthetic:"


def resolve_scenes(scenes: Sequence[Path], folder: Path) -> List[Path]:
    """`synthetic:<layout>` (ring, occluded, sparse-objects) -> the embedded procedural scene of that layout,
    generated into `folder/synthetic-<layout>` on first use; other entries are scene folders, returned as given."""
    from hpgs_ns.synthetic_scene import LAYOUTS, make_scene

    out = []
    for scene in scenes:
        text = str(scene)
        if not text.startswith(SYNTHETIC):
            out.append(Path(scene))
            continue
        layout = text[len(SYNTHETIC):]
        if layout not in LAYOUTS:
            raise SystemExit(f"hpgs bench: unknown synthetic scene {text!r}; use synthetic:" + " or synthetic:".join(LAYOUTS))
        path = folder / f"synthetic-{layout}"
        if not (path / "sparse" / "0").is_dir():
            CONSOLE.print(f"generating {text} into {path}")
            make_scene(path, layout=layout, seed=0, overwrite=True)
        out.append(path)
    return out


def result_path(out: Path, scene: Path, protocol: str, name: str, seed: int) -> Path:
    return out / scene.name / protocol / name / f"seed{seed}.json"


def run_log_path(out: Path, scene: Path, protocol: str, name: str, seed: int) -> Path:
    return out / "_runs" / f"{scene.name}-{protocol}-{name}-seed{seed}.log"


def run_folder(run_root: Path, scene: Path, protocol: str, name: str, seed: int) -> Path:
    """Where ns-train writes one run (its `--output-dir`/`--experiment-name`/method/`--timestamp`)."""
    return run_root / scene.name / "hpgs" / f"{protocol}-{name}-seed{seed}"


def train_args(bench: Bench, scene: Path, protocol: Protocol, name: str, seed: int, run_root: Path) -> List[str]:
    initial = bench.initial_views or protocol.initial_views
    selector, rounds = name, protocol.max_rounds
    if name == "initial":
        selector, rounds = "random", 0
    elif name == "all":
        selector, rounds, initial = "random", 0, 100000
    args = [
        sys.executable, "-m", "nerfstudio.scripts.train", "hpgs",
        "--data", str(scene), "--output-dir", str(run_root), "--experiment-name", scene.name,
        "--timestamp", f"{protocol.name}-{name}-seed{seed}", "--vis", "tensorboard",
        "--machine.seed", str(seed),
        "--max-num-iterations", str(protocol.steps), "--steps-per-save", str(protocol.steps),
        "--steps-per-eval-all-images", str(10 * protocol.steps),
        "--steps-per-eval-image", str(10 * protocol.steps),
        "--pipeline.datamanager.num-initial-views", str(initial),
        "--pipeline.datamanager.initial-views", protocol.initial_mode,
        "--pipeline.datamanager.max-rounds", str(rounds),
        "--pipeline.datamanager.selector", selector,
        "--pipeline.datamanager.seed", str(seed),
        "--pipeline.datamanager.eval-each-round", "True",
        # ns-eval's JSON, written by the training process (hpgs_ns/trainer.py): no second start-up per run
        "--final-eval-json", str(run_folder(run_root, scene, protocol.name, name, seed) / "eval.json"),
        "--pipeline.model.rasterizer", bench.rasterizer,
    ]
    if protocol.select_at:
        args += ["--pipeline.datamanager.select-at", *map(str, protocol.select_at)]
    else:
        args += ["--pipeline.datamanager.select-every", str(protocol.select_every)]
    if bench.downscale_factor is not None:
        args += ["--pipeline.datamanager.dataparser.downscale-factor", str(bench.downscale_factor)]
    if bench.reset_after_add:
        args += ["--pipeline.datamanager.reset-after-add", "True"]
    if bench.strict_init:
        args += ["--pipeline.datamanager.strict-init", "True"]
    return args + shlex.split(bench.extra_args)


def run_settings(bench: Bench, protocol: Protocol) -> dict:
    """What changes a run's numbers without changing its result path (checked when a sweep resumes)."""
    return {
        "steps": protocol.steps,
        "initial_views": bench.initial_views or protocol.initial_views,
        "downscale_factor": bench.downscale_factor,
        "rasterizer": bench.rasterizer,
        "extra_args": bench.extra_args,
    }


def run_one(
    bench: Bench, scene: Path, protocol: Protocol, name: str, seed: int, env: Optional[Dict[str, str]] = None
) -> dict:
    """Train and evaluate one run in a subprocess with environment `env` (default: this process's)."""
    run_root = bench.out / "_runs"
    cmd = train_args(bench, scene, protocol, name, seed, run_root)
    run_dir = run_folder(run_root, scene, protocol.name, name, seed)
    # A run killed half-way left events and checkpoints there; timing and eval must see only this run's.
    shutil.rmtree(run_dir, ignore_errors=True)
    start = time.perf_counter()
    log_path = run_log_path(bench.out, scene, protocol.name, name, seed)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        # wait4 gives this child's own peak RSS (getrusage(RUSAGE_CHILDREN) would be the max over all runs).
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        tail = "\n".join(log_path.read_text().strip().splitlines()[-15:])
        raise SystemExit(f"hpgs bench: training failed ({shlex.join(cmd)}):\n{tail}")
    metrics = json.loads((run_dir / "eval.json").read_text())
    selected = json.loads((run_dir / "selected_views.json").read_text())
    rounds = selected["rounds"]
    return {
        "scene": scene.name,
        "protocol": protocol.name,
        "selector": name,
        "seed": seed,
        "steps": protocol.steps,
        "test": metrics["results"],
        "num_test_views": len(selected["test"]),
        "num_views_final": len(selected["active"]),
        "psnr_per_round": [
            {"step": r["step"], "num_views_before": r["num_active"] - len(r["chosen"]), "test_psnr": r["test_psnr_before"]}
            for r in rounds
        ],
        "wall_seconds": wall,
        "selection_seconds": float(sum(r["seconds"] for r in rounds)),
        "selection_seconds_per_round": [r["seconds"] for r in rounds],
        "selection_work": summed_work(rounds),
        **train_timing(run_dir),
        "peak_memory_mb": {"host_rss": usage.ru_maxrss / 1024, "gpu_allocated": selected.get("peak_gpu_memory_mb")},
        "initial_views": selected["initial"],
        "chosen_views": [v for r in rounds for v in r["chosen"]],
        "command": shlex.join(cmd),
        "settings": run_settings(bench, protocol),
        "device": device_name(),
    }


def summed_work(rounds: List[dict]) -> Dict[str, float]:
    """The selectors' work counters (`Selection.work`) summed over a run's rounds."""
    total: Dict[str, float] = {}
    for r in rounds:
        for key, value in r.get("work", {}).items():
            total[key] = total.get(key, 0.0) + value
    return total


def work_table(rows: List[dict]) -> str:
    """What selection computed and what it skipped, per selector (mean over runs): renders at the size the
    selector needs vs the dataset's, Fisher's frustum-culled (view, Gaussian) pairs vs all of them."""
    groups: Dict[Tuple[str, str, str], List[dict]] = {}
    for r in rows:
        if r.get("selection_work"):
            groups.setdefault((r["scene"], r["protocol"], r["selector"]), []).append(r)
    if not groups:
        return ""
    lines = [
        "| scene | protocol | selector | views rendered | pixels vs full size | pairs vs unculled | backward passes | forwards | selection (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def mean(group: List[dict], key: str) -> float:
        return sum(g["selection_work"].get(key, 0.0) for g in group) / len(group)

    for (scene, protocol, sel), group in sorted(groups.items()):
        full, pairs_all = mean(group, "pixels_full_resolution"), mean(group, "pairs_unculled")
        pixels = f"{100 * mean(group, 'pixels_rendered') / full:.0f}%" if full else "-"
        pairs = f"{100 * mean(group, 'pairs_differentiated') / pairs_all:.0f}%" if pairs_all else "-"
        seconds = sum(g["selection_seconds"] for g in group) / len(group)
        lines.append(
            f"| {scene} | {protocol} | {sel} | {mean(group, 'views_rendered'):.0f} | {pixels} | {pairs} | "
            f"{mean(group, 'backward_passes'):.0f} | {mean(group, 'model_forwards'):.0f} | {seconds:.1f} |"
        )
    return "\n".join(lines) + "\n"


def train_timing(run_dir: Path) -> dict:
    """Per-iteration training time from the run's tensorboard events.

    nerfstudio logs a running mean of "Train Iter (time)" every few steps; rounds are single slow iterations,
    so the median of the logged means is the typical per-iteration time, selection excluded."""
    try:
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    except ImportError:
        return {}
    times, totals = [], []
    for events in run_dir.glob("events.out.tfevents.*"):
        acc = EventAccumulator(str(events), size_guidance={"scalars": 0})
        acc.Reload()
        tags = acc.Tags().get("scalars", [])
        if "Train Iter (time)" in tags:
            times += [e.value for e in acc.Scalars("Train Iter (time)")]
        if "Train Total (time)" in tags:
            totals += [e.value for e in acc.Scalars("Train Total (time)")]
    times.sort()
    return {
        "train_iter_ms_median": 1000 * times[len(times) // 2] if times else None,
        "train_total_seconds": max(totals) if totals else None,
    }


def device_name() -> str:
    import torch

    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else f"cpu x{os.cpu_count()}"


def load_results(out: Path) -> List[dict]:
    return [json.loads(p.read_text()) for p in sorted(out.glob("*/*/*/seed*.json"))]


def _mean_std(values: Sequence[float]) -> Tuple[float, float]:
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else 0.0
    return mean, std


def markdown_table(rows: List[dict]) -> str:
    """Mean +- std over seeds per (scene, protocol, selector)."""
    groups: Dict[Tuple[str, str, str], List[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["protocol"], r["selector"]), []).append(r)
    lines = [
        "| scene | protocol | selector | seeds | views | PSNR | SSIM | LPIPS | devices | wall (s) | selection (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    order = {name: i for i, name in enumerate(list(SELECTORS) + list(REFERENCES))}
    for (scene, protocol, sel), group in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], order.get(kv[0][2], 99))):
        cells = []
        for key in ("psnr", "ssim", "lpips"):
            m, s = _mean_std([g["test"][key] for g in group])
            digits = 2 if key == "psnr" else 3
            # One seed has no spread to show (a "± 0.00" would read as a measured one).
            cells.append(f"{m:.{digits}f} ± {s:.{digits}f}" if len(group) > 1 else f"{m:.{digits}f}")
        wall, _ = _mean_std([g["wall_seconds"] for g in group])
        selt, _ = _mean_std([g["selection_seconds"] for g in group])
        views = group[0]["num_views_final"]
        devices = device_counts(group)
        lines.append(
            f"| {scene} | {protocol} | {sel} | {len(group)} | {views} | {' | '.join(cells)} | {devices} | {wall:.0f} | {selt:.1f} |"
        )
    return "\n".join(lines) + "\n"


def short_device(row: dict) -> str:
    """`NVIDIA H100 80GB HBM3` -> `H100`, `cpu x2` -> `cpu`."""
    return str(row.get("device", "?")).replace("NVIDIA ", "").split()[0]


def device_counts(group: List[dict]) -> str:
    """`H100 x2, H200`: wall times are only comparable on one device, and sweeps span sessions and machines."""
    counts: Dict[str, int] = {}
    for g in group:
        counts[short_device(g)] = counts.get(short_device(g), 0) + 1
    return ", ".join(name if n == 1 else f"{name} x{n}" for name, n in sorted(counts.items()))


def make_plots(rows: List[dict], out: Path) -> List[Path]:
    """PSNR vs wall time per selector, PSNR vs number of views, per (scene, protocol)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    keys = sorted({(r["scene"], r["protocol"]) for r in rows})
    for scene, protocol in keys:
        group = [r for r in rows if r["scene"] == scene and r["protocol"] == protocol]
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
        # One marker per device: run times are only comparable on one device.
        markers = dict(zip(sorted({short_device(r) for r in group}), "o^sDvP"))
        for i, sel in enumerate(sorted({r["selector"] for r in group})):
            rs = [r for r in group if r["selector"] == sel]
            for n, r in enumerate(rs):
                ax1.scatter(r["wall_seconds"], r["test"]["psnr"], s=30, color=f"C{i}",
                            marker=markers[short_device(r)], label=sel if n == 0 else None)
            if sel in REFERENCES:
                continue
            for k, r in enumerate(rs):
                pts = [(p["num_views_before"], p["test_psnr"]) for p in r["psnr_per_round"] if p["test_psnr"] is not None]
                pts.append((r["num_views_final"], r["test"]["psnr"]))
                ax2.plot(*zip(*pts), marker="o", ms=3, color=f"C{i}",
                         label=sel if k == 0 else None, alpha=0.8)
        ax1.set(xlabel="wall time (s)", ylabel="test PSNR (dB)", title=f"{scene} / {protocol}: PSNR vs run time")
        ax2.set(xlabel="training views", ylabel="test PSNR (dB)", title="PSNR as views are added")
        handles, labels = ax1.get_legend_handles_labels()
        if len(markers) > 1:
            for device, marker in markers.items():
                handles.append(ax1.scatter([], [], marker=marker, color="grey", s=30))
                labels.append(device)
        ax1.legend(handles, labels, fontsize=8)
        ax2.legend(fontsize=8)
        fig.tight_layout()
        path = out / f"{scene}-{protocol}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
        map_path = camera_map(group, out / f"{scene}-{protocol}-cameras.png")
        if map_path is not None:
            paths.append(map_path)
    return paths


def camera_centres(scene: Path) -> Optional[Dict[str, Tuple[float, float]]]:
    """Top-down 2D positions of a scene's cameras by image name: COLMAP centres projected on the plane of their
    two principal directions (the capture's ground plane for orbit-like captures)."""
    import numpy as np

    from hpgs_ns.colmap_model import camera_pose, read_images

    images = read_images(Path(scene) / "sparse" / "0")
    if images is None:
        return None
    names = [im.name for im in images.values()]
    centres = np.stack([camera_pose(im)[1] for im in images.values()])
    centred = centres - centres.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    xy = centred @ vt[:2].T
    return {n: (float(x), float(y)) for n, (x, y) in zip(names, xy)}


def camera_map(group: List[dict], path: Path) -> Optional[Path]:
    """One panel per selector (first seed): all cameras, the initial views, and the chosen ones numbered."""
    import matplotlib.pyplot as plt

    runs = [r for r in sorted(group, key=lambda r: r["seed"]) if r["selector"] not in REFERENCES and r["chosen_views"]]
    if not runs:
        return None
    data = shlex.split(runs[0]["command"])
    scene = Path(data[data.index("--data") + 1]) if "--data" in data else None
    pos = camera_centres(scene) if scene is not None and scene.is_dir() else None
    if not pos:
        return None
    first = {}
    for r in runs:
        first.setdefault(r["selector"], r)
    fig, axes = plt.subplots(1, len(first), figsize=(3.6 * len(first), 3.6), squeeze=False)
    all_xy = list(pos.values())
    for ax, (sel, r) in zip(axes[0], sorted(first.items())):
        ax.scatter(*zip(*all_xy), s=6, c="lightgrey", label="withheld / test")
        ax.scatter(*zip(*[pos[n] for n in r["initial_views"] if n in pos]), s=12, c="C0", label="initial")
        chosen = [(k, pos[name]) for k, name in enumerate(r["chosen_views"], 1) if name in pos]
        if chosen:
            ax.scatter(*zip(*[xy for _, xy in chosen]), s=30, c="C3", label="added (in order)")
        for k, xy in chosen:
            ax.annotate(str(k), xy, fontsize=8, xytext=(3, 3), textcoords="offset points")
        ax.set(title=f"{sel} (seed {r['seed']})", xticks=[], yticks=[], aspect="equal")
    # Below the panels: inside one it would hide cameras.
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
