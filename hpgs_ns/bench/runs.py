"""`hpgs bench`: the command, and launching its runs (each one a real `ns-train hpgs` in a subprocess).

One run per (scene, protocol, selector, seed), plus two reference rows per (scene, protocol, seed):
`initial` (no views added) and `all` (every training view). Each run writes
`OUT/<scene>/<protocol>/<selector>/seed<k>.json`; runs whose JSON exists are skipped, so a killed sweep resumes.
`hpgs bench --report-only` rebuilds the markdown table and the plots from whatever JSON is there (`report`).
`hpgs bench --stress pose-noise exposure corrupt` also runs every scene perturbed (`stress`): copies
`OUT/_scenes/<scene>+<perturbation>`, results under `OUT/<scene>+<perturbation>/`, and `stress.md` beside `table.md`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shlex
import shutil
import subprocess
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple

import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from hpgs_ns.atomic_write import write_json_atomic, write_text_atomic
from hpgs_ns.bench.executors import ExecutorConfig, make_executor
from hpgs_ns.bench.protocols import DEFAULT_SELECTORS, PROTOCOLS, REFERENCES, Protocol, scaled
from hpgs_ns.bench.report import load_results, make_plots, markdown_table, stress_plot, stress_table, work_table
from hpgs_ns.bench.stress import PerturbationName, StressConfig, StressError, stressed_scenes
from hpgs_ns.dataparser import SceneDataError, scene_dataparser
from hpgs_ns.ns_train import ns_train_command

CONSOLE = Console(stderr=True)


@dataclass
class Bench:
    """Benchmark selectors (test PSNR/SSIM/LPIPS, wall and selection time, memory) on scenes."""

    scenes: List[Path] = field(default_factory=list)
    """Scene folders (Mip-NeRF 360 layout with sparse/0, read by `mipnerf360`; or transforms.json, read by
    `nerfstudio-data`), or `synthetic:ring`, `synthetic:occluded`, `synthetic:sparse-objects` for the embedded
    procedural scenes (generated into OUT/_scenes on first use)."""
    out: Path = Path("benchmarks/results/bench")
    """Results folder (one JSON per run; table and plots beside)."""
    selectors: List[str] = field(default_factory=lambda: list(DEFAULT_SELECTORS))
    """Selectors to run (any registered name)."""
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
            try:
                scene_dataparser(scene)
            except SceneDataError as err:
                raise SystemExit(f"hpgs bench: {err}") from None
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
    from hpgs_ns.scenes.synthetic import LAYOUTS, make_scene

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
    """The `ns-train hpgs` command of one run."""
    initial = bench.initial_views or protocol.initial_views
    selector, rounds = name, protocol.max_rounds
    if name == "initial":
        selector, rounds = "random", 0
    elif name == "all":
        selector, rounds, initial = "random", 0, 100000
    datamanager: Dict[str, Any] = {
        "num-initial-views": initial,
        "initial-views": protocol.initial_mode,
        "max-rounds": rounds,
        "selector": selector,
        "seed": seed,
        "eval-each-round": True,
    }
    if protocol.select_at:
        datamanager["select-at"] = protocol.select_at
    else:
        datamanager["select-every"] = protocol.select_every
    if bench.reset_after_add:
        datamanager["reset-after-add"] = True
    if bench.strict_init:
        datamanager["strict-init"] = True
    return ns_train_command(
        scene, run_root, scene.name, f"{protocol.name}-{name}-seed{seed}", protocol.steps,
        # ns-eval's JSON, written by the training process (hpgs_ns/trainer.py): no second start-up per run
        trainer={"machine.seed": seed, "final-eval-json": run_folder(run_root, scene, protocol.name, name, seed) / "eval.json"},
        datamanager=datamanager, model={"rasterizer": bench.rasterizer}, extra=shlex.split(bench.extra_args),
        dataparser=scene_dataparser(scene),
        dataparser_options={} if bench.downscale_factor is None else {"downscale-factor": bench.downscale_factor},
    )


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


Job = Tuple[Path, Protocol, str, int]  # (scene, protocol, selector or reference name, seed), as `Bench.jobs()` lists


def run_label(job: Job) -> str:
    scene, protocol, name, seed = job
    return f"{scene.name}/{protocol.name}/{name}/seed{seed}"


def sweep_worker(item: Tuple[Any, Job], env: Dict[str, str]) -> dict:
    """Worker side: train and evaluate one run, write its JSON, return `{"result": ...}` or `{"error", "log"}`."""
    bench, (scene, protocol, name, seed) = item
    try:
        result = run_one(bench, scene, protocol, name, seed, env={**os.environ, **env})
    except (Exception, SystemExit) as exc:  # run_one exits on a failed training; keep the worker alive
        return {"error": str(exc), "log": str(run_log_path(bench.out, scene, protocol.name, name, seed))}
    write_json_atomic(result_path(bench.out, scene, protocol.name, name, seed), result)
    return {"result": result}


def run_sweep(bench: Any, jobs: Sequence[Job], config: ExecutorConfig) -> None:
    """Driver side: run `jobs` on the configured executor; every finished run's JSON ends up under `bench.out`.

    Every worker writes its run's JSON itself (temp file + rename) as well: a run that finishes while the driver is
    dead (Slurm jobs outlive it) is kept, and a re-run of the sweep submits only the runs with no JSON."""
    if not jobs:
        return
    # Absolute paths: Ray workers and Slurm jobs need not start in this folder.
    bench = replace(bench, out=bench.out.resolve(), scenes=[s.resolve() for s in bench.scenes])
    jobs = [(scene.resolve(), protocol, name, seed) for scene, protocol, name, seed in jobs]
    executor = make_executor(config, bench.out)
    CONSOLE.print(f"hpgs bench: {len(jobs)} runs to do ({config.executor})")
    failures: List[str] = []
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=CONSOLE) as progress:
        bar = progress.add_task("runs", total=len(jobs))
        for done in executor.map(sweep_worker, [(bench, job) for job in jobs]):
            job = jobs[done.index]
            value = done.value or {"error": done.error, "log": None}
            if "result" in value:
                result = value["result"]
                path = result_path(bench.out, job[0], job[1].name, job[2], job[3])
                if not path.exists():  # the worker wrote it unless it ran on another filesystem
                    write_json_atomic(path, result)
                progress.console.print(
                    f"{run_label(job)}  PSNR {result['test']['psnr']:.2f}  wall {result['wall_seconds']:.0f} s  "
                    f"selection {result['selection_seconds']:.1f} s"
                )
            else:
                failures.append(f"{run_label(job)} (log: {value['log']})")
                last = (value["error"] or "").strip().splitlines()
                progress.console.print(f"[red]failed: {failures[-1]}: {last[-1] if last else ''}")
            progress.advance(bar)
    if failures:
        raise SystemExit(
            f"hpgs bench: {len(failures)} of {len(jobs)} runs failed (the others' results are saved; "
            "re-run to retry only these):\n  " + "\n  ".join(failures)
        )
