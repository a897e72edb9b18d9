"""`hpgs bench`: the command, and launching its runs (each one a real `ns-train hpgs` in a subprocess).

One run per (scene, protocol, selector, seed), plus two reference rows per (scene, protocol, reference seed):
`initial` (no views added) and `all` (every training view) (`names`). Each run writes its `results.RunResult` to
`OUT/<scene>/<protocol>/<selector>/seed<k>.json` (`seed<k>-repeat<r>.json` for `--repeats`); runs whose JSON
exists are skipped, so a killed sweep resumes, and a finished run made with other settings (code, preference
model, selector options, schedule, dataparser options, ...) is a one-line error rather than mixed in.
`--final-set first-seed|all` then trains each finished selector run's final views from step 0 (`final_set_jobs`):
`OUT/<scene>/<protocol>/<selector>/final-set/seed<k>.json`, redone when its run's views have changed since.
`hpgs bench --report-only` rebuilds the tables and the plots from whatever JSON is there (`report`), and with
`--results-page docs/results.md` the results page.
Scenes come from `--scenes` (folders) or a suite (`--suite real6`, `suites`), which also gives each scene's
dataparser and options. `hpgs bench --stress pose-noise exposure corrupt` also runs every scene perturbed
(`stress`): copies `OUT/_scenes/<scene>+<perturbation>`, results under `OUT/<scene>+<perturbation>/`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import gzip
import json
import os
import shlex
import shutil
import socket
import subprocess
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, NamedTuple, Optional, Sequence, Tuple

import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from hpgs_lab import mps as cuda_mps
from hpgs_lab import provenance
from hpgs_lab.executors import ExecutorConfig, make_executor, runs_per_device
from hpgs_lab.names import ALL, FINAL_SET, INITIAL, REFERENCES, is_reference
from hpgs_lab.protocols import DEFAULT_SELECTORS, PROTOCOLS, Protocol, scaled
from hpgs_lab.report import write_report
from hpgs_lab.results import Metrics, Provenance, RoundPsnr, RunResult, SourceRun, Timing, ViewMetrics, start_label
from hpgs_lab.stress import PerturbationName, StressConfig, perturbed_copy
from hpgs_lab.suites import SYNTHETIC, Scene, load_suite, scene_from_folder
from hpgs_ns.atomic_write import atomic_path
from hpgs_ns.errors import UserError
from hpgs_ns.ns_train import SELECTION_PREFIX, ns_train_command
from hpgs_ns.selection.early_stop import DEFAULT_GAIN_MODEL
from hpgs_ns.selection.log import SelectionLog
from hpgs_ns.selection.records import RoundRecord

CONSOLE = Console(stderr=True)


def uses_preference_model(name: str) -> bool:
    """Whether selector `name` scores with a preference model: its config class says (`SelectorConfig`'s facts)."""
    from hpgs_ns.selectors.base import SelectionError
    from hpgs_ns.selectors.registry import selector_class

    if is_reference(name):
        return False
    try:
        return bool(getattr(selector_class(name), "uses_preference_model", False))
    except SelectionError:  # not a selector: its run fails with that line, reported with the sweep's failures
        return False


@dataclass
class Bench:
    """Benchmark selectors (test PSNR/SSIM/LPIPS, wall and selection time, memory) on scenes."""

    scenes: List[Path] = field(default_factory=list)
    """Scene folders (Mip-NeRF 360 layout with sparse/0, read by `mipnerf360`; or transforms.json, read by
    `nerfstudio-data`), or `synthetic:ring`, `synthetic:occluded`, `synthetic:sparse-objects` for the embedded
    procedural scenes (generated into OUT/_scenes on first use)."""
    suite: Optional[str] = None
    """A suite of scenes with their dataparsers and options: a shipped one (`real6`: the six real captures in
    shared/data at half size, plus a synthetic smoke scene; `tune6`: the six tuning captures; `real12`: real6's six
    and tune6's; `judge13`: real6's six and seven captures never tuned on, where tuned settings are judged; `all19`:
    judge13 and tune6) or a .toml file (see `hpgs_lab/suites.py`)."""
    suite_scenes: List[str] = field(default_factory=list)
    """Only these scenes of the suite (default: all)."""
    data_root: Path = Path("../shared/data")
    """Where the suite's scene paths are."""
    out: Path = Path("benchmarks/results/bench")
    """Results folder (one JSON per run; tables and plots beside)."""
    selectors: List[str] = field(default_factory=lambda: list(DEFAULT_SELECTORS))
    """Selectors to run (any registered name)."""
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])
    """Seeds: initial random views, selector randomness and torch. A seed pairs runs of different selectors."""
    reference_seeds: Optional[List[int]] = None
    """Seeds of the `initial`/`all` reference rows (default: the same as `--seeds`)."""
    repeats: int = 1
    """Run each (scene, selector, seed) this many times: the spread of repeats is the noise a seed cannot fix
    (gsplat's non-deterministic backward, densification)."""
    protocols: List[Literal["hpgs", "fisherrf"]] = field(default_factory=lambda: ["hpgs"])
    """View-addition protocols."""
    references: bool = True
    """Also run the `initial` (no additions) and `all` (every training view) rows."""
    reference_rows: List[Literal["initial", "all"]] = field(default_factory=lambda: list(REFERENCES))
    """Which reference rows --references runs (e.g. only `all`: each row is one more full training run)."""
    final_set: Literal["none", "first-seed", "all"] = "none"
    """Also run a `final-set` reference for selector runs: the run's final views (initial and chosen) trained from
    step 0 with its seed, steps and settings and no rounds; the report's schedule cost is its PSNR minus the run's.
    `first-seed`: the runs of the first of --seeds (repeat 0); `all`: every selector run (each one more training
    run). They run after the sweep's runs, from the finished runs' JSON, into
    `<selector>/final-set/seed<k>.json`; one whose run has other views now (re-run) is redone. Independent of
    --no-references."""
    step_scale: float = 1.0
    """Multiply every step count (e.g. 0.01 for a CPU smoke run)."""
    initial_views: Optional[int] = None
    """Override the protocol's number of initial views (small scenes)."""
    max_runs: Optional[int] = None
    """Stop after this many new runs (fit a sweep into a time budget; re-run to continue)."""
    downscale_factor: Optional[int] = None
    """Dataparser downscale factor for every scene (overrides the suite's; e.g. 2 for the shared bonsai-device images_2)."""
    rasterizer: Literal["auto", "gsplat", "cpu"] = "auto"
    """Rasterizer for all runs."""
    reset_after_add: bool = False
    """Reset the model and its schedules after each added view (FisherRF; `--pipeline.model.restarts.every-round`);
    results go under `<protocol>-reset`."""
    strict_init: bool = False
    """Start from seed points seen by two initial views only (`--pipeline.datamanager.seed-points colmap-initial`; needs
    COLMAP tracks); results go under `<protocol>-strict`."""
    extra_args: str = ""
    """Extra `ns-train hpgs` arguments for every run (quoted). A finished run made with other arguments is an
    error on resume, not skipped: pass another `--out`."""
    preference_models: Optional[Path] = None
    """A folder of per-scene preference models, `<scene>.pt`, each trained without that scene (leave one scene out):
    `hpgs`, `condorcet` and `blend` runs of a scene use its model, so no run scores views with a model that saw
    the scene."""
    blend_weights: Optional[Path] = None
    """Per-scene weights of the `blend` selector, each fitted without that scene: the JSON of
    `benchmarks/candidate_scores.py --selectors farthest hpgs --out FILE` (its `combination_loso.weights`). Scenes
    it does not name use the shipped weights, which were fitted on the logged scenes only."""
    stop_when_gain_below: Optional[float] = None
    """Stop each run's selection once the next view is predicted to gain less than this many dB (`early_stop`);
    results go under `<protocol>-stop<X>`."""
    gain_model: Optional[Path] = None
    """The gain calibration for --stop-when-gain-below (`benchmarks/early_stop.py --write-model`)."""
    log_candidate_scores: bool = False
    """Also log every selector's score of every candidate and each candidate's render error at every round
    (`<stem>-candidates.jsonl.gz` beside each result; for tuning selectors offline, `benchmarks/candidate_scores.py`)."""
    accept_code_change: bool = False
    """Keep finished runs whose only difference is the code (e.g. a sweep built across commits whose changes
    cannot move the numbers); the report then says how many code versions are behind the comparisons."""
    report_only: bool = False
    """Only rebuild the tables and plots from existing JSON."""
    results_page: Optional[Path] = None
    """Also write the results page (paired comparisons, repeat noise, throughput) to this markdown file, e.g.
    docs/results.md."""
    stress: List[PerturbationName] = field(default_factory=list)
    """Also run every scene under these perturbations of its training views (copies in OUT/_scenes)."""
    stress_config: StressConfig = field(default_factory=StressConfig)
    """Strength and seed of each perturbation."""
    cluster: tyro.conf.OmitArgPrefixes[ExecutorConfig] = field(default_factory=ExecutorConfig)
    """Where the runs execute (`--executor local|ray|slurm`, `--runs-per-gpu N` and their options)."""

    def main(self) -> None:
        page = self.results_page
        if not self.report_only:
            self.run_all(self.scene_list())  # its UserErrors (suite, scene, stress) print as one line
        if not any(self.out.glob("*/*/*/seed*.json")):
            raise UserError(f"hpgs bench: no results under {self.out}; run a sweep first or pass the --out it wrote")
        for path in write_report(self.out, results_page=page):
            CONSOLE.print(f"wrote {path}")

    def scene_list(self) -> List[Scene]:
        """The scenes to run: `--scenes` folders, then the suite's; synthetic ones generated, stress copies made."""
        scenes = [scene_from_folder(Path(s)) for s in self.scenes]
        if self.suite is not None:
            scenes += load_suite(self.suite, self.data_root, self.suite_scenes)
        scenes = resolve_scenes(scenes, self.out / "_scenes")
        if self.downscale_factor is not None:
            scenes = [s.with_options(**{"downscale-factor": str(self.downscale_factor)}) for s in scenes]
        if self.stress:
            copies = []
            for scene in scenes:
                for name in self.stress:
                    copy = perturbed_copy(scene.path, name, self.out / "_scenes", self.stress_config)
                    CONSOLE.print(f"stress: {copy}")
                    copies.append(dataclasses.replace(scene, name=f"{scene.name}+{name}", path=copy))
            scenes += copies
        return scenes

    def jobs(self, scenes: Optional[Sequence[Scene]] = None) -> List[Job]:
        """Every run, seed by seed: a sweep cut short has whole (scene, seed) pairs of every selector first."""
        scenes = list(scenes) if scenes is not None else [scene_from_folder(Path(s)) for s in self.scenes]
        reference_seeds = self.seeds if self.reference_seeds is None else self.reference_seeds
        jobs = []
        for seed in sorted(set(self.seeds) | set(reference_seeds if self.references else [])):
            for scene in scenes:
                for pname in self.protocols:
                    protocol = scaled(PROTOCOLS[pname], self.step_scale)
                    if self.reset_after_add:
                        protocol = dataclasses.replace(protocol, name=f"{protocol.name}-reset")
                    if self.strict_init:
                        protocol = dataclasses.replace(protocol, name=f"{protocol.name}-strict")
                    if self.stop_when_gain_below is not None:
                        protocol = dataclasses.replace(protocol, name=f"{protocol.name}-stop{self.stop_when_gain_below:g}")
                    names = list(self.selectors) if seed in self.seeds else []
                    names += list(dict.fromkeys(self.reference_rows)) if self.references and seed in reference_seeds else []
                    for name in names:
                        for repeat in range(self.repeats if name not in REFERENCES else 1):
                            jobs.append(Job(scene, protocol, name, seed, repeat))
        return jobs

    def run_all(self, scenes: Optional[Sequence[Scene]] = None) -> None:
        todo = []
        for job in self.jobs(scenes):
            path = job.result_path(self.out)
            if not path.exists():
                todo.append(job)
                continue
            check_settings(self, job, path)
        fallback = sorted({j.scene.name for j in todo if uses_preference_model(j.name) and self.preference_models is not None
                           and scene_preference_model(self, j) is None})
        if fallback:
            CONSOLE.print(f"hpgs bench: no model in {self.preference_models} for {', '.join(fallback)}: they run the shipped "
                          "default preference model, which never saw their renders", soft_wrap=True)
        seen = default_model_scenes(self, todo)
        if seen:
            CONSOLE.print(f"[yellow]hpgs bench: the default preference model was trained on renders of {', '.join(seen)}; "
                          "for leave-one-scene-out numbers pass --preference-models benchmarks/results/pref_models")
        todo = self.within_max_runs(todo, self.max_runs, "runs")
        check_commands(self, todo)  # a run ns-train would refuse fails here, before any run starts
        failed: Optional[UserError] = None
        try:
            run_sweep(self, todo, self.cluster)
        except UserError as err:  # the runs that did finish still get their final-set references
            failed = err
        try:
            self.run_final_sets(scenes, None if self.max_runs is None else self.max_runs - len(todo))
        except UserError as err:
            if failed is None:
                raise
            raise UserError(f"{failed}; and {err}") from None
        if failed is not None:
            raise failed

    def within_max_runs(self, todo: List[Job], budget: Optional[int], what: str) -> List[Job]:
        """The first `budget` jobs of `todo` (None: all), saying how many --max-runs leaves for the next call."""
        if budget is None or len(todo) <= budget:
            return todo
        budget = max(budget, 0)
        CONSOLE.print(f"[yellow]--max-runs {self.max_runs}: {len(todo) - budget} {what} left; run again to continue")
        return todo[:budget]

    def final_set_jobs(self, scenes: Optional[Sequence[Scene]] = None) -> List[Job]:
        """A `final-set` job for every selector run that --final-set names and whose result exists: its final
        views (initial and chosen, read from the result) and its seed and repeat. Runs not finished yet have none."""
        if self.final_set == "none":
            return []
        jobs = []
        for job in self.jobs(scenes):
            if job.name in REFERENCES or (self.final_set == "first-seed" and (job.seed != self.seeds[0] or job.repeat)):
                continue
            path = job.result_path(self.out)
            if not path.exists():
                continue
            run = RunResult.from_json(path)
            views = run.final_views
            if not views or len(views) != run.num_views_final:  # results too old to name every view
                CONSOLE.print(f"[yellow]hpgs bench: {path} does not name its {run.num_views_final} final views; no final-set for it")
                continue
            jobs.append(Job(job.scene, job.protocol, FINAL_SET, job.seed, job.repeat, source=job.name, views=tuple(views)))
        return jobs

    def final_set_todo(self, scenes: Optional[Sequence[Scene]] = None) -> List[Job]:
        """The final-set jobs to run: those without a result, and those whose result trained other views than its
        run has now (the run was re-run: stale, redone). A result made with other settings is an error, as for runs."""
        todo = []
        for job in self.final_set_jobs(scenes):
            path = job.result_path(self.out)
            if not path.exists():
                todo.append(job)
                continue
            check_settings(self, job, path)
            source = RunResult.from_json(path).final_set_of
            if source is None or sorted(source.views) != list(job.views):
                CONSOLE.print(f"[yellow]hpgs bench: {path} trained other views than its run has now; redoing it")
                todo.append(job)
        return todo

    def run_final_sets(self, scenes: Optional[Sequence[Scene]] = None, budget: Optional[int] = None) -> None:
        """Run the final-set jobs left to do (`final_set_todo`), at most `budget` of them (None: all)."""
        todo = self.within_max_runs(self.final_set_todo(scenes), budget, "final-set runs")
        check_commands(self, todo, what="final-set run")
        run_sweep(self, todo, self.cluster, what="final-set runs")


def check_settings(bench: Bench, job: Job, path: Path) -> None:
    """A finished run made with other settings than `job` would be now is a one-line error naming what differs."""
    made_with = RunResult.from_json(path).provenance.settings  # None in results older than this check
    settings = run_settings(bench, job)
    changed_keys = [k for k in sorted(set(made_with or {}) | set(settings)) if (made_with or {}).get(k) != settings.get(k)]
    if made_with is not None and changed_keys and not (bench.accept_code_change and changed_keys == ["code"]):
        changed = ", ".join(changed_keys)
        raise UserError(
            f"hpgs bench: {path} was made with other settings ({changed}); pass another --out to keep both, "
            "delete it to re-run" + (", or --accept-code-change if the code change cannot move the numbers"
                                     if changed_keys == ["code"] else "")
        )


class Job(NamedTuple):
    """One run of a sweep."""

    scene: Scene
    protocol: Protocol
    name: str
    """A selector, a reference row (`names.REFERENCES`), or `names.FINAL_SET`."""
    seed: int
    repeat: int = 0
    source: str = ""
    """A final-set job's selector run (its seed and repeat are the job's)."""
    views: Tuple[str, ...] = ()
    """A final-set job's views: its run's final views, sorted."""

    @property
    def label(self) -> str:
        return f"{self.scene.name}/{self.protocol.name}/{self.folder}/{self.stem}"

    @property
    def folder(self) -> str:
        """The result's folder under the protocol: the name, or `<selector>/final-set` beside the run it belongs to."""
        return f"{self.source}/{FINAL_SET}" if self.name == FINAL_SET else self.name

    @property
    def stem(self) -> str:
        return f"seed{self.seed}" + (f"-repeat{self.repeat}" if self.repeat else "")

    def result_path(self, out: Path) -> Path:
        return out / self.scene.name / self.protocol.name / self.folder / f"{self.stem}.json"

    def log_path(self, out: Path) -> Path:
        return out / "_runs" / f"{self.scene.name}-{self.protocol.name}-{self.folder.replace('/', '-')}-{self.stem}.log"

    def run_folder(self, run_root: Path) -> Path:
        """Where ns-train writes the run (its `--output-dir`/`--experiment-name`/method/`--timestamp`)."""
        return run_root / self.scene.name / "hpgs" / f"{self.protocol.name}-{self.folder.replace('/', '-')}-{self.stem}"


def resolve_scenes(scenes: Sequence[Scene], folder: Path) -> List[Scene]:
    """`synthetic:<layout>` (ring, occluded, sparse-objects) scenes -> the embedded procedural scene of that
    layout, generated into `folder/synthetic-<layout>` on first use; other scenes are returned as given."""
    from hpgs_ns.scenes.synthetic import LAYOUTS, make_scene

    out = []
    for scene in scenes:
        text = str(scene.path)
        if not text.startswith(SYNTHETIC):
            out.append(scene)
            continue
        layout = text[len(SYNTHETIC):]
        if layout not in LAYOUTS:
            raise UserError(f"hpgs bench: unknown synthetic scene {text!r}; use synthetic:" + " or synthetic:".join(LAYOUTS))
        path = folder / f"synthetic-{layout}"
        if not (path / "sparse" / "0").is_dir():
            CONSOLE.print(f"generating {text} into {path}")
            make_scene(path, layout=layout, seed=0, overwrite=True)
        out.append(dataclasses.replace(scene, path=path))
    return out


def train_args(bench: Bench, job: Job, run_root: Path) -> List[str]:
    """The `ns-train hpgs` command of one run."""
    protocol, name, seed = job.protocol, job.name, job.seed
    initial = bench.initial_views or protocol.initial_views
    selector, rounds = name, protocol.max_rounds
    if name in (INITIAL, FINAL_SET):
        selector, rounds = "random", 0
    elif name == ALL:
        selector, rounds, initial = "random", 0, 100000
    datamanager: Dict[str, Any] = {"num-initial-views": initial, "initial-views": protocol.initial_mode, "seed": seed}
    if name == FINAL_SET:  # its run's final views, named, from step 0
        datamanager = {"num-initial-views": len(job.views), "initial-view-names": list(job.views), "seed": seed}
    selection: Dict[str, Any] = {"max-rounds": rounds, "selector": selector, "eval-each-round": True}
    if protocol.select_at:
        selection["select-at"] = protocol.select_at
    else:
        selection["select-every"] = protocol.select_every
    if bench.strict_init:
        datamanager["seed-points"] = "colmap-initial"
    if bench.stop_when_gain_below is not None and not is_reference(name):
        selection["stop-when-gain-below"] = bench.stop_when_gain_below
        if bench.gain_model is not None:
            selection["gain-model"] = Path(bench.gain_model).resolve()
    if bench.log_candidate_scores and not is_reference(name):
        selection["log-candidate-scores"] = True
    selection.update(scene_selector_options(bench, job))
    return ns_train_command(
        job.scene.path, run_root, job.scene.name, job.run_folder(run_root).name, protocol.steps,
        # ns-eval's JSON, written by the training process (hpgs_ns/trainer.py): no second start-up per run
        trainer={"machine.seed": seed, "final-eval-json": job.run_folder(run_root) / "eval.json"},
        datamanager=datamanager, selection=selection,
        model={"rasterizer": bench.rasterizer, **({"restarts.every-round": True} if bench.reset_after_add else {})},
        extra=shlex.split(bench.extra_args), dataparser=job.scene.dataparser, dataparser_options=job.scene.option_dict(),
    )


# Options whose values differ from run to run of one scene and protocol: masked, runs that differ only in them are
# parsed once (their values are the sweep's own: seeds, folders, counts and names it writes itself).
PER_RUN_OPTIONS = frozenset({
    "--timestamp", "--machine.seed", "--final-eval-json", "--pipeline.datamanager.seed",
    "--pipeline.datamanager.num-initial-views", "--pipeline.datamanager.initial-view-names",
    f"--{SELECTION_PREFIX}selector", f"--{SELECTION_PREFIX}max-rounds",
})


def command_shape(args: Sequence[str]) -> Tuple[str, ...]:
    """`args` with the values of `PER_RUN_OPTIONS` replaced by one `*`."""
    shape: List[str] = []
    masking = False
    for word in args:
        if word.startswith("--"):
            masking = word in PER_RUN_OPTIONS
        elif masking:
            if shape[-1] != "*":
                shape.append("*")
            continue
        shape.append(word)
    return tuple(shape)


def check_commands(bench: Bench, jobs: Sequence[Job], what: str = "run") -> None:
    """Refuse, in one line, a sweep any of whose `ns-train hpgs` commands ns-train would refuse while it parses
    them (an option the dataparser lacks, a value of the wrong type, one a config's check rejects), before any run
    starts: each run would otherwise fail minutes in, after the runs before it. One in-process parse per distinct
    command shape (`command_shape`); the selectors, masked there, are checked by name."""
    from hpgs_ns.selectors.registry import selector_names

    known = selector_names()
    for name in dict.fromkeys(j.name for j in jobs if j.name != FINAL_SET and not is_reference(j.name)):
        if name not in known:
            raise UserError(f"hpgs bench: --selectors {name}: unknown selector; choose one of {', '.join(known)} (or "
                            f"install the package that registers it); no {what} was launched")
    shapes: Dict[Tuple[str, ...], Job] = {}
    for job in jobs:
        args = train_args(bench, job, bench.out / "_runs")
        args = args[args.index("nerfstudio.scripts.train") + 2:]  # after `python -m nerfstudio.scripts.train hpgs`
        if shapes.setdefault(command_shape(args), job) is not job:
            continue
        reason = ns_train_refusal(args)
        if reason is not None:
            raise UserError(f"hpgs bench: {job.label}: ns-train hpgs refuses its arguments: {reason}"
                            f"{refusal_fix(bench, job, reason)}; no {what} was launched")


def ns_train_refusal(args: Sequence[str]) -> Optional[str]:
    """Why `ns-train hpgs ARGS` would stop while parsing ARGS (tyro's parse of the `hpgs` method's config, as
    ns-train runs it, with the configs' own checks), in one line; None if it parses. Nothing is trained."""
    import io

    from hpgs_ns.method_config import hpgs

    printed = io.StringIO()
    cli = tyro.conf.SuppressFixed[tyro.conf.FlagConversionOff[type(hpgs.config)]]  # ns-train's markers
    try:
        with provenance.PARSE_LOCK, contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed), \
                warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tyro.cli(cli, default=hpgs.config, args=list(args), prog="ns-train hpgs")
    except UserError as err:  # a config's own check: its line names the fix
        return str(err)
    except SystemExit:  # tyro drew its error box
        return stop_reason(printed.getvalue().splitlines()) or "no reason given"
    return None


def refusal_fix(bench: Bench, job: Job, reason: str) -> str:
    """Where the option a refusal names came from, and what to do: the scene's suite options or --extra-args."""
    import re

    flags = {word.split("=")[0] for word in re.findall(r"--[\w.-]+", reason)}
    if flags & {f"--{k}" for k in job.scene.option_dict()}:
        return (f"; it is an option of scene {job.scene.name!r} in the suite: fix or drop it (`ns-train hpgs "
                f"{job.scene.dataparser} --help` lists {job.scene.dataparser}'s options)")
    if flags & {w.split("=")[0] for w in shlex.split(bench.extra_args)}:
        return "; it is in --extra-args: fix or drop it (`ns-train hpgs --help` lists the options)"
    return ""


BOX_BORDER = "│┃║|"
BOX_RULE = set("─━═-╭╮╰╯┌┐└┘┏┓┗┛╔╗╚╝+ ")


def stop_reason(lines: Sequence[str]) -> str:
    """Why a run's `ns-train` stopped, in one line, from the end of its output: its last `error: ...` line; else,
    where tyro drew its error box, the box's first paragraph without the border; else the last line."""
    lines = [line.strip().strip(BOX_BORDER).strip() for line in lines]

    def rule(line: str) -> bool:
        return bool(line) and (line[0] in "╭╰┌└" or set(line) <= BOX_RULE)

    said = [line for line in lines if line.startswith("error: ")]
    if said:
        return said[-1]
    if any("For full helptext" in line for line in lines):
        tops = [i for i, line in enumerate(lines) if line.startswith(("╭", "┌"))]  # a box in UTF-8 (a run's log)
        start = tops[-1] if tops else next((i for i, line in enumerate(lines) if rule(line)), -1)  # or in ASCII
        paragraph = []
        for line in lines[start + 1:]:
            if not line or rule(line):
                if paragraph:
                    break
                continue
            paragraph.append(line)
        text = " ".join(paragraph)
        head, colon, named = text.partition(": ")
        if head == "Unrecognized options" and colon:
            # tyro lists an unknown option's value words too (`--nosuch-option, 1`): name the options
            options = [w for w in named.split(", ") if w.startswith("-")]
            text = f"{head}: {', '.join(options or named.split(', '))}"
        if text:
            return text
    return next((line for line in reversed(lines) if line and not rule(line)), "no output")


def run_settings(bench: Bench, job: Job) -> dict:
    """What changes a run's numbers without changing its result path (checked when a sweep resumes): the
    schedule, the dataparser and its options, the code that trains and selects, the selector's options and its
    preference model."""
    selector = None if is_reference(job.name) else job.name
    own = [w for k, v in scene_selector_options(bench, job).items() for w in (f"--{SELECTION_PREFIX}{k}", str(v))]
    options = provenance.selector_options(selector, shlex.split(bench.extra_args) + own) if selector else None
    return {
        "steps": job.protocol.steps,
        "initial_views": bench.initial_views or job.protocol.initial_views,
        "dataparser": job.scene.dataparser,
        "dataparser_options": job.scene.option_dict(),
        "rasterizer": bench.rasterizer,
        "extra_args": bench.extra_args,
        "code": provenance.code_hash(selector),
        "selector_options": options,
        "preference_model": provenance.preference_model_hash(selector, options) if selector else None,
        "stop_when_gain_below": bench.stop_when_gain_below,
        "gain_model": gain_model_hash(bench) if bench.stop_when_gain_below is not None else None,
    }


def scene_selector_options(bench: Bench, job: Job) -> Dict[str, Any]:
    """The selection options this scene's selector gets from the sweep (as suffixes of `ns_train.SELECTION_PREFIX`):
    its preference model (--preference-models) and blend's weights (--blend-weights), both fitted without it."""
    options: Dict[str, Any] = {}
    model = scene_preference_model(bench, job)
    if model is not None:
        options[f"{job.name}.model"] = model
    options.update({f"{job.name}.{k}": v for k, v in scene_blend_weights(bench, job).items()})
    return options


def default_model_training_scenes() -> frozenset:
    """The scenes whose renders trained the shipped default preference model (its checkpoint's record)."""
    from hpgs_ns.selectors.preference_features import DEFAULT_MODEL

    return _model_training_scenes(Path(DEFAULT_MODEL))


@functools.lru_cache(maxsize=4)
def _model_training_scenes(path: Path) -> frozenset:
    # read once per model file: scene_preference_model asks for every job, several times a sweep
    import torch  # only here: reading the checkpoint's record needs no model

    meta = torch.load(path, map_location="cpu", weights_only=True).get("meta") or {}
    return frozenset((meta.get("training_data") or {}).get("oracle_scenes") or [])


def default_model_scenes(bench: Bench, jobs: Sequence[Job]) -> List[str]:
    """Scenes of `jobs` whose preference-model runs would use the shipped default although it saw their renders."""
    if bench.preference_models is not None or not any(uses_preference_model(j.name) for j in jobs):
        return []
    trained_on = default_model_training_scenes()
    return sorted({j.scene.name for j in jobs if uses_preference_model(j.name) and j.scene.name in trained_on})


def scene_preference_model(bench: Bench, job: Job) -> Optional[Path]:
    """The scene's own preference model under --preference-models, for selectors that run one (else None: the
    shipped default, also for a scene without its own model that the default never saw, which is then already a
    model trained without it)."""
    if bench.preference_models is None or not uses_preference_model(job.name):
        return None
    folder = Path(bench.preference_models)
    if not folder.is_dir() or not any(folder.glob("*.pt")):
        raise UserError(f"hpgs bench: --preference-models {folder} is not a folder of <scene>.pt models; train them "
                        "leaving one scene out (docs/benchmark.md) or drop --preference-models")
    path = (folder / f"{job.scene.name}.pt").resolve()
    if not path.is_file():
        if job.scene.name not in default_model_training_scenes():
            return None
        raise UserError(f"hpgs bench: no preference model {path} for scene {job.scene.name!r}, and the shipped default "
                        "saw its renders; train one without that scene (leave one scene out) or drop --preference-models")
    return path


def keep_candidate_log(log: Path, keep: Path) -> None:
    """Copy a run's candidate_scores.jsonl beside its result, gzipped: the logs are most of a results folder's bytes
    (~3x smaller so), and results travel to the GPU machine."""
    with atomic_path(keep) as tmp, open(log, "rb") as src, gzip.GzipFile(tmp, "wb", mtime=0) as dst:
        shutil.copyfileobj(src, dst)


def keep_worst_views(metrics: dict, run_dir: Path, result: Path) -> List[dict]:
    """Copy the final eval's worst-view JPEGs beside the run's result (`<stem>-worst<k>.jpg`): the run folder
    (checkpoints) is often left on the GPU machine, and one view can move a scene's mean by a dB."""
    for stale in result.parent.glob(f"{result.stem}-worst*.jpg"):  # an earlier run's, which kept more views
        stale.unlink()
    kept = []
    for rank, view in enumerate(metrics.get("worst_views", [])):
        source = run_dir / view["image"]
        if not source.is_file():
            continue
        target = result.with_name(f"{result.stem}-worst{rank}.jpg")
        with atomic_path(target, suffix=".jpg") as tmp:
            shutil.copyfile(source, tmp)
        kept.append({"name": view["name"], "psnr": view["psnr"], "image": target.name})
    return kept


def fitted_weights(name: str) -> Dict[str, str]:
    """The options of selector `name` fitted on candidate logs ({logged selector: option}; its config class says,
    `SelectorConfig.fitted_weights`: blend's farthest and hpgs weights); empty for any other row."""
    from hpgs_ns.selectors.base import SelectionError
    from hpgs_ns.selectors.registry import selector_class

    if is_reference(name):
        return {}
    try:
        return dict(getattr(selector_class(name), "fitted_weights", {}))
    except SelectionError:  # not a selector: its run fails with that line, reported with the sweep's failures
        return {}


def scene_blend_weights(bench: Bench, job: Job) -> Dict[str, float]:
    """The fitted weights of this scene's selector from --blend-weights (`fitted_weights`: blend's), as option names
    (empty: the shipped weights, or a selector with none)."""
    fitted = fitted_weights(job.name) if bench.blend_weights is not None else {}
    if not fitted:
        return {}
    try:
        table = json.loads(Path(bench.blend_weights).read_text())["combination_loso"]["weights"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise UserError(f"hpgs bench: --blend-weights {bench.blend_weights} is not a candidate_scores.py JSON with "
                         f"combination_loso.weights ({err}); write one with benchmarks/candidate_scores.py --out") from None
    weights = table.get(job.scene.name)
    if weights is None:
        return {}
    if set(weights) != set(fitted):
        raise UserError(f"hpgs bench: --blend-weights {bench.blend_weights} combines {', '.join(sorted(weights))}; "
                        f"{job.name} takes {' and '.join(fitted)} (candidate_scores.py --selectors {' '.join(fitted)})")
    return {option.replace("_", "-"): float(weights[key]) for key, option in fitted.items()}


def gain_model_hash(bench: Bench) -> str:
    path = Path(bench.gain_model) if bench.gain_model is not None else DEFAULT_GAIN_MODEL
    return provenance.file_hash(path) if path.is_file() else "missing"


class TrainingFailed(UserError, RuntimeError):
    """One run's `ns-train` exited with an error; `tail` holds the end of its log."""

    def __init__(self, message: str, tail: str = ""):
        super().__init__(message)
        self.tail = tail


def run_one(bench: Bench, job: Job, env: Optional[Dict[str, str]] = None, sweep: Optional[Dict[str, Any]] = None) -> RunResult:
    """Train and evaluate one run in a subprocess with environment `env` (default: this process's). `sweep`:
    the sweep's `id` (the report's throughput groups runs by it) and `runs_per_gpu`, how many runs shared the
    device at a time (1: its times are its own)."""
    sweep = sweep or {}
    run_root = bench.out / "_runs"
    cmd = train_args(bench, job, run_root)
    run_dir = job.run_folder(run_root)
    # A run killed half-way left events and checkpoints there; timing and eval must see only this run's.
    shutil.rmtree(run_dir, ignore_errors=True)
    started = time.time()
    start = time.perf_counter()
    log_path = job.log_path(bench.out)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        status, usage, under_mps = wait_watching_mps(proc.pid, env if env is not None else dict(os.environ))
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        lines = log_path.read_text(errors="replace").strip().splitlines()
        tail, last = lines[-15:], stop_reason(lines[-60:])
        raise TrainingFailed(f"hpgs bench: training {job.label} failed ({last}); its log: {log_path}", "\n".join(tail))
    log = run_dir / "candidate_scores.jsonl"
    if log.is_file():
        keep_candidate_log(log, job.result_path(bench.out).with_name(f"{job.stem}-candidates.jsonl.gz"))
    metrics = json.loads((run_dir / "eval.json").read_text())
    worst_views = keep_worst_views(metrics, run_dir, job.result_path(bench.out))
    selected = SelectionLog.read(run_dir)
    rounds = selected.rounds
    timing = train_timing(run_dir)
    return RunResult(
        scene=job.scene.name,
        protocol=job.protocol.name,
        selector=job.name,
        seed=job.seed,
        repeat=job.repeat,
        smoke=job.scene.smoke,
        steps=job.protocol.steps,
        data=str(job.scene.path),
        dataparser=job.scene.dataparser,
        test=Metrics.from_dict(metrics["results"]),
        # per-view metrics, where the trainer's final eval records them
        test_views=[ViewMetrics.from_dict(v) for v in metrics.get("test_views", [])],
        num_test_views=len(selected.test),
        num_train_views=len(selected.active) + len(selected.withheld),
        num_views_final=len(selected.active),
        psnr_at_round_steps=dict(selected.test_psnr_at_round_steps),
        psnr_per_round=[RoundPsnr(r.step, r.num_active - len(r.chosen), r.test_psnr_before) for r in rounds],
        timing=Timing(
            wall_seconds=wall,
            selection_seconds=float(sum(r.seconds for r in rounds)),
            selection_seconds_per_round=[r.seconds for r in rounds],
            train_iter_ms_median=timing.get("train_iter_ms_median"),
            train_total_seconds=timing.get("train_total_seconds"),
            started_at=started,
            sweep_id=sweep.get("id"),
            runs_per_gpu=sweep.get("runs_per_gpu", 1),
            peak_host_rss_mb=usage.ru_maxrss / 1024,
            peak_gpu_allocated_mb=selected.peak_gpu_memory_mb,
            gpu=(env or os.environ).get("CUDA_VISIBLE_DEVICES"),
            mps=under_mps,
        ),
        selection_work=summed_work(rounds),
        worst_views=worst_views,
        num_gaussians=metrics.get("num_gaussians"),
        near_culled=metrics.get("near_culled"),
        seed_points=start_label(selected.seed_points, selected.random_start),
        initial_views=selected.initial,
        chosen_views=selected.chosen,
        provenance=Provenance(command=shlex.join(cmd), device=device_name(), git_commit=provenance.git_commit(),
                              libraries=library_versions(), settings=run_settings(bench, job)),
        final_set_of=SourceRun(job.source, job.seed, job.repeat, list(job.views)) if job.name == FINAL_SET else None,
    )


def wait_watching_mps(pid: int, env: Dict[str, str], every: float = 2.0):
    """Wait for child `pid`; meanwhile ask its MPS daemon, if it has one, whether the child became its client.
    Returns (wait status, rusage, MPS observed: True, False, or None where no daemon answers)."""
    seen: Optional[bool] = None
    while True:
        # wait4 gives this child's own peak RSS (getrusage(RUSAGE_CHILDREN) would be the max over all runs).
        done, status, usage = os.wait4(pid, os.WNOHANG)
        if done:
            return status, usage, seen
        now = cuda_mps.observed(pid, env)
        if now or (now is None and seen is None):  # seen, or no daemon where this run looks: nothing more to learn
            seen = now
            break
        seen = False if now is False else seen
        time.sleep(every)
    _, status, usage = os.wait4(pid, 0)
    return status, usage, seen


def summed_work(rounds: Sequence[RoundRecord]) -> Dict[str, float]:
    """The selectors' work counters (`Selection.work`) summed over a run's rounds."""
    total: Dict[str, float] = {}
    for r in rounds:
        for key, value in r.work.items():
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


def library_versions() -> Dict[str, Optional[str]]:
    from importlib.metadata import PackageNotFoundError, version

    import hpgs_ns

    out: Dict[str, Optional[str]] = {"hpgs_ns": hpgs_ns.__version__}
    for name in ("torch", "gsplat", "nerfstudio"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


def sweep_worker(item: Tuple[Bench, Job, Dict[str, Any]], env: Dict[str, str]) -> dict:
    """Worker side: train and evaluate one run, write its JSON, return `{"result": RunResult}` or
    `{"error", "log"}` (the error with the end of the run's log, for the driver's out-of-memory hint)."""
    bench, job, sweep = item
    try:
        result = run_one(bench, job, env={**os.environ, **env}, sweep=sweep)
    except Exception as exc:  # keep the worker alive for the other runs
        tail = getattr(exc, "tail", "")
        return {"error": str(exc) + (f"\n{tail}" if tail else ""), "log": str(job.log_path(bench.out)),
                "mps": cuda_mps.PIPE in env, "gpu": env.get("CUDA_VISIBLE_DEVICES")}
    result.to_json(job.result_path(bench.out))
    return {"result": result}


def run_sweep(bench: Bench, jobs: Sequence[Job], config: ExecutorConfig, what: str = "runs") -> None:
    """Driver side: run `jobs` on the configured executor; every finished run's JSON ends up under `bench.out`.

    Every worker writes its run's JSON itself (temp file + rename) as well: a run that finishes while the driver is
    dead (Slurm jobs outlive it) is kept, and a re-run of the sweep submits only the runs with no JSON."""
    if not jobs:
        return
    # Absolute paths: Ray workers and Slurm jobs need not start in this folder.
    bench = replace(bench, out=bench.out.resolve())
    jobs = [job._replace(scene=dataclasses.replace(job.scene, path=job.scene.path.resolve())) for job in jobs]
    executor = make_executor(config, bench.out)
    # host-time.pid: two sweeps started in the same second on one machine stay apart
    sweep = {"id": f"{socket.gethostname()}-{int(time.time())}.{os.getpid()}", "runs_per_gpu": runs_per_device(config)}
    CONSOLE.print(f"hpgs bench: {len(jobs)} {what} to do ({config.executor}, {sweep['runs_per_gpu']} per device)")
    failures: List[str] = []
    errors: List[str] = []
    todo, retried = list(jobs), False
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=CONSOLE) as progress:
        bar = progress.add_task("runs", total=len(jobs))
        while todo:
            ended_by_mps: List[Job] = []
            # closing: the executor's MPS daemons are quit as soon as the loop ends, also on an exception
            with contextlib.closing(executor.map(sweep_worker, [(bench, job, sweep) for job in todo])) as results:
                for done in results:
                    job = todo[done.index]
                    value = done.value or {"error": done.error, "log": None}
                    if "result" in value:
                        result = value["result"]
                        path = job.result_path(bench.out)
                        if not path.exists():  # the worker wrote it unless it ran on another filesystem
                            result.to_json(path)
                        progress.console.print(
                            f"{job.label}  PSNR {result.test.psnr:.2f}  wall {result.timing.wall_seconds:.0f} s  "
                            f"selection {result.timing.selection_seconds:.1f} s"
                        )
                        progress.advance(bar)
                        continue
                    last = (value["error"] or "").strip().splitlines()
                    if value.get("mps") and not retried and cuda_mps.looks_like_mps_fault(value["error"] or ""):
                        ended_by_mps.append(job)
                        progress.console.print(f"[yellow]ended under MPS: {job.label}: {last[-1] if last else ''}")
                        continue
                    failures.append(f"{job.label} (log: {value['log']})")
                    errors.append(value["error"] or "")
                    progress.console.print(f"[red]failed: {failures[-1]}: {last[-1] if last else ''}")
                    progress.advance(bar)
            todo, retried = ended_by_mps, True
            if todo:
                # A fatal fault in one MPS client ends every client of that GPU's server: run those again, once.
                CONSOLE.print(f"hpgs bench: a GPU fault under MPS ended {len(todo)} run(s) sharing its GPU; running "
                              "them again, once (a run that fails again is listed as failed)", soft_wrap=True)
    if failures:
        raise UserError(
            f"hpgs bench: {len(failures)} of {len(jobs)} runs failed: {'; '.join(failures)}; the others' results are "
            "saved: re-run to retry only these" + out_of_memory_hint(errors, sweep["runs_per_gpu"])
        )


def out_of_memory_hint(errors: Sequence[str], runs_per_gpu: int) -> str:
    """A closing line when runs died of GPU memory: the fix is fewer runs sharing a GPU (12 runs of ~100-view
    scenes at once overflowed an 80 GB H100), not a bug in the run."""
    n = sum("out of memory" in e.lower() or "OutOfMemoryError" in e for e in errors)
    if not n:
        return ""
    return (f"; {n} of them ran out of GPU memory: re-run with a lower --runs-per-gpu (now {runs_per_gpu}; "
            "other processes on the same GPU count too)")
