"""What one benchmark run records: `RunResult`, written by `hpgs bench` (one JSON per run) and read by the
report, the statistics, the early-stop fitting and the scripts in `benchmarks/`.

Versions of the JSON:

* 1 (no `version` key): the flat layout results were written in before this module. It grew over time, so old
  files lack some keys (the oldest have no `repeat`, `smoke`, `settings`, `provenance`, `selection_work`, ...);
  `V1_DEFAULTS` is the one place that says what a missing key means. The scene's folder is read from the
  recorded `ns-train` command, its dataparser from the recorded settings.
* 2: nested parts (`test`, `timing`, `provenance`), the scene's `data` folder and `dataparser` as fields, and
  per-test-view metrics (`test_views`, empty when the trainer did not record them). A final-set reference
  (`hpgs bench --final-set`) also has `final_set_of`, the run it trained the final views of (absent elsewhere,
  and in version-2 files written before it: None). Every run written since 0.4 also has `worst_views`, the
  lowest-PSNR test views whose renders (ground truth | render) were kept as JPEGs beside the JSON, and
  `num_gaussians` (empty and None in files written before them).

`RunResult.from_json` reads every version; `to_json` writes the current one.
"""

from __future__ import annotations

import json
import shlex
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional

from hpgs_lab.names import is_reference
from hpgs_ns.atomic_write import write_json_atomic
from hpgs_ns.errors import UserError

VERSION = 2

# What a key absent from a version-1 file means: runs written before the key existed.
V1_DEFAULTS: Dict[str, Any] = {
    "repeat": 0,  # --repeats came later: every older run is a first repeat
    "smoke": False,  # smoke scenes came with suites
    "steps": None,
    "num_test_views": None,
    "num_train_views": None,
    "psnr_at_round_steps": {},  # eval-each-round came later
    "selection_work": {},
    "selection_seconds_per_round": [],
    "train_iter_ms_median": None,
    "train_total_seconds": None,
    "peak_memory_mb": {},
    "started_at": None,
    "sweep_id": None,
    "runs_per_gpu": 1,  # before --runs-per-gpu every run had its device alone
    "settings": None,  # not checked on resume
    "provenance": {},
    "device": "?",
    "initial_views": [],
    "chosen_views": [],
    "psnr_per_round": [],
    "command": "",
}


class ResultError(UserError, ValueError):
    """A result file that cannot be read."""


def _pick(cls, data: Mapping[str, Any]) -> Dict[str, Any]:
    """The keys of `data` that are fields of dataclass `cls`."""
    return {f.name: data[f.name] for f in fields(cls) if f.name in data}


@dataclass(frozen=True)
class Metrics:
    """ns-eval's means over the test views, and their spread over the views."""

    psnr: float
    ssim: float
    lpips: float
    psnr_std: Optional[float] = None
    ssim_std: Optional[float] = None
    lpips_std: Optional[float] = None
    num_rays_per_sec: Optional[float] = None
    num_rays_per_sec_std: Optional[float] = None
    fps: Optional[float] = None
    fps_std: Optional[float] = None

    def value(self, metric: str) -> float:
        """`psnr`, `ssim` or `lpips` by name."""
        return float(getattr(self, metric))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Metrics:
        picked = _pick(cls, data)
        wrong = [k for k, v in picked.items() if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)))]
        if wrong:
            raise TypeError(f"test metric {wrong[0]} is {picked[wrong[0]]!r}, not a number")
        return cls(**picked)


@dataclass(frozen=True)
class ViewMetrics:
    """One test view's metrics at the end of training; the render's depth over its opaque pixels (10th percentile,
    median; `hpgs_ns.trainer.view_depths`) and what lies in front of its camera (`front_*`,
    `hpgs_ns.render.front.describe_front`) where the run recorded them."""

    name: str
    psnr: float
    ssim: float
    lpips: float
    depth_p10: Optional[float] = None
    depth_median: Optional[float] = None
    front_gaussians: Optional[int] = None
    front_cover: Optional[float] = None
    front_large: Optional[int] = None
    front_large_sigma_median: Optional[float] = None
    front_large_sigma_max: Optional[float] = None
    front_large_on_surface: Optional[float] = None
    front_large_on_two_surfaces: Optional[float] = None
    front_large_in_view: Optional[float] = None
    front_large_suspect: Optional[float] = None

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ViewMetrics:
        """From a final eval's (or a result's) test-view entry; keys that are not fields are left out."""
        return cls(**_pick(cls, data))


@dataclass(frozen=True)
class RoundPsnr:
    """Test PSNR just before a selection round (None where the run did not evaluate at round steps)."""

    step: int
    num_views_before: int
    test_psnr: Optional[float]


@dataclass(frozen=True)
class Timing:
    """Where the run's time went, and whether it had its device alone (see `report.tables.solo`)."""

    wall_seconds: float
    selection_seconds: float
    selection_seconds_per_round: List[float] = field(default_factory=list)
    train_iter_ms_median: Optional[float] = None
    """Median of nerfstudio's logged running mean of one training iteration (selection excluded)."""
    train_total_seconds: Optional[float] = None
    started_at: Optional[float] = None
    """Unix time the run started."""
    sweep_id: Optional[str] = None
    """`host-time.pid` of the sweep that ran it: runs of one machine share its device."""
    runs_per_gpu: int = 1
    """How many runs the sweep put on one device at a time (1: its times are its own)."""
    peak_host_rss_mb: Optional[float] = None
    peak_gpu_allocated_mb: Optional[float] = None
    gpu: Optional[str] = None
    """The run's CUDA_VISIBLE_DEVICES (an index, or a UUID under MPS): runs on one GPU share it."""
    mps: Optional[bool] = None
    """Whether the run was seen as a client of a CUDA MPS server (None: no MPS daemon where it looked)."""


@dataclass(frozen=True)
class Provenance:
    """What made the numbers: the command, the code, the libraries, the device, the settings checked on resume."""

    command: str = ""
    device: str = "?"
    git_commit: Optional[str] = None
    libraries: Dict[str, Optional[str]] = field(default_factory=dict)
    """Package -> version (hpgs_ns, torch, gsplat, nerfstudio)."""
    settings: Optional[Dict[str, Any]] = None
    """`runs.run_settings` as the run was made (None for runs older than that check)."""


@dataclass(frozen=True)
class SourceRun:
    """The selector run a final-set reference belongs to: its result is `<selector>/seed<seed>[-repeat<r>].json`
    beside the final-set's folder, and `views` are the final views it trained (sorted), to tell a final-set
    made from other views (the run was re-run since) from a current one."""

    selector: str
    seed: int
    repeat: int = 0
    views: List[str] = field(default_factory=list)


@dataclass(frozen=True)
class RunResult:
    """One benchmark run: one (scene, protocol, selector or reference row, seed, repeat)."""

    scene: str
    protocol: str
    selector: str
    """A selector, or a reference row (`names.REFERENCES`)."""
    seed: int
    test: Metrics
    timing: Timing
    repeat: int = 0
    smoke: bool = False
    """A smoke-check scene: tabulated, never part of a comparison."""
    steps: Optional[int] = None
    data: Optional[str] = None
    """The scene folder as passed to `ns-train --data` (relative to where the sweep ran)."""
    dataparser: Optional[str] = None
    """The dataparser subcommand (None where the run did not record it)."""
    num_test_views: Optional[int] = None
    num_train_views: Optional[int] = None
    num_views_final: int = 0
    initial_views: List[str] = field(default_factory=list)
    chosen_views: List[str] = field(default_factory=list)
    """Views added, in the order they were chosen."""
    psnr_per_round: List[RoundPsnr] = field(default_factory=list)
    psnr_at_round_steps: Dict[int, float] = field(default_factory=dict)
    """Test PSNR at every round step, rounds that did not run included (`eval-each-round`)."""
    selection_work: Dict[str, float] = field(default_factory=dict)
    """The selector's work counters summed over rounds (`Selection.work`)."""
    test_views: List[ViewMetrics] = field(default_factory=list)
    """Per test view metrics at the end (empty for runs that did not record them)."""
    num_gaussians: Optional[int] = None
    """The splat's size at the end (None in files written before it)."""
    near_culled: Optional[int] = None
    """Gaussians the floater guard (`--pipeline.model.near-cull.*`) removed over the run (None: it was off)."""
    seed_points: Optional[str] = None
    """What the splat started from (`start_label`: the `--pipeline.datamanager.seed-points` mode as resolved, `auto`
    being colmap or active, or `random` where it gave no points); None in files written before it (see `start`)."""
    worst_views: List[Dict[str, Any]] = field(default_factory=list)
    """The lowest-PSNR test views, each {name, psnr, image}: `image` is a JPEG beside this JSON (ground truth |
    render), to look at what moved a run's mean."""
    provenance: Provenance = field(default_factory=Provenance)
    final_set_of: Optional[SourceRun] = None
    """For a final-set reference (`selector` is `final-set`): the run whose final views it trained from step 0."""

    @property
    def is_reference(self) -> bool:
        return is_reference(self.selector)

    @property
    def start(self) -> Optional[str]:
        """The seed points it trained from (`start_label`) where recorded; older runs predate that, so it is read
        from their command: `--pipeline.model.random-init True` is `random`, else the named `seed-points` (or
        `strict-init True`), else `colmap`, the default then, which is a random start on a capture without a point
        cloud (said for nerfstudio-data and Blender captures, whose files may lack one). None without a command."""
        if self.seed_points:
            return self.seed_points
        words = shlex.split(self.provenance.command or "")
        if not words:
            return None
        named = command_options(words)
        if named.get("--pipeline.model.random-init") == "True":
            return "random"
        if named.get("--pipeline.datamanager.strict-init") == "True":
            return "colmap-initial"
        mode = named.get("--pipeline.datamanager.seed-points", "colmap")
        without_colmap = {"nerfstudio-data", "blender-data"}  # dataparsers whose captures may have no point cloud
        if mode == "colmap" and (without_colmap & set(words) or self.dataparser in without_colmap):
            return "colmap (random without a point cloud)"
        return mode

    @property
    def final_views(self) -> List[str]:
        """The views active at the end (initial and chosen), sorted."""
        return sorted(self.initial_views + self.chosen_views)

    @property
    def device(self) -> str:
        return self.provenance.device

    def to_dict(self) -> Dict[str, Any]:
        """The current version's JSON object."""
        out: Dict[str, Any] = {"version": VERSION}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.name in WRITTEN_WHEN_SET:
                continue
            if f.name == "psnr_at_round_steps":
                value = {str(k): v for k, v in value.items()}  # JSON keys are strings
            elif f.name in ("test", "timing", "provenance"):
                value = {g.name: getattr(value, g.name) for g in fields(value)}
            elif f.name == "psnr_per_round":
                value = [{g.name: getattr(v, g.name) for g in fields(v)} for v in value]
            elif f.name == "test_views":  # the depths only where recorded: older results rewrite unchanged
                value = [{g.name: getattr(v, g.name) for g in fields(v) if getattr(v, g.name) is not None} for v in value]
            elif f.name == "final_set_of":
                value = {g.name: getattr(value, g.name) for g in fields(value)}
            out[f.name] = value
        return out

    def to_json(self, path: Path) -> Path:
        """Write (temp file, then rename) as the current version."""
        return write_json_atomic(Path(path), self.to_dict())

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RunResult:
        if not isinstance(data, Mapping):
            raise ResultError(f"not a benchmark result (a JSON {type(data).__name__}, not an object)")
        version = data.get("version", 1)
        try:
            if version == 1:
                data = _from_v1(data)
            elif version != VERSION:
                newer = isinstance(version, int) and not isinstance(version, bool) and version > VERSION
                raise ResultError(f"result version {version!r} is {'newer than' if newer else 'not one'} this hpgs_ns "
                                  f"reads ({VERSION}); {'upgrade hpgs_ns' if newer else 're-run it'}")
        except ResultError:
            raise
        except (KeyError, TypeError, AttributeError, ValueError) as err:
            raise ResultError(f"not a benchmark result ({type(err).__name__}: {err})") from None
        wrong = [k for k, kind in RESULT_TYPES.items() if k in data and not isinstance(data[k], kind)]
        if wrong:
            raise ResultError(f"not a benchmark result ({wrong[0]} is {data[wrong[0]]!r})")
        try:
            return cls(
                **{k: data[k] for k in ("scene", "protocol", "selector", "seed")},
                test=Metrics.from_dict(data["test"]),
                timing=Timing(**_pick(Timing, data["timing"])),
                **{k: data[k] for k in ("repeat", "smoke", "steps", "data", "dataparser", "num_test_views",
                                        "num_train_views", "num_views_final", "initial_views", "chosen_views",
                                        "selection_work", "worst_views", "num_gaussians", "near_culled", "seed_points")
                   if k in data},
                psnr_per_round=[RoundPsnr(**_pick(RoundPsnr, p)) for p in data.get("psnr_per_round", [])],
                psnr_at_round_steps={int(k): float(v) for k, v in (data.get("psnr_at_round_steps") or {}).items()},
                test_views=[ViewMetrics.from_dict(v) for v in data.get("test_views", [])],
                provenance=Provenance(**_pick(Provenance, data.get("provenance", {}))),
                final_set_of=SourceRun(**_pick(SourceRun, data["final_set_of"])) if data.get("final_set_of") else None,
            )
        except (KeyError, TypeError, AttributeError, ValueError) as err:
            raise ResultError(f"not a benchmark result ({type(err).__name__}: {err})") from None

    @classmethod
    def from_json(cls, path: Path) -> RunResult:
        """Read a result of any version (older ones get `V1_DEFAULTS` for what they lack)."""
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except ResultError as err:
            raise ResultError(f"{path}: {err}; re-run it or move it out of the results folder") from None
        except (OSError, ValueError) as err:
            raise ResultError(f"{path} is not readable JSON ({err}); re-run it or move it out of the results "
                              "folder") from None


def start_label(mode: Optional[str], random_start: bool) -> Optional[str]:
    """What a run's splat started from, for the report: its `seed-points` mode as resolved, `random` where that
    gave no points (`colmap` without a point cloud, `random-init`), `<mode> (random at step 0)` where `active` or
    `colmap-initial` found too few. None where the run did not record it."""
    if mode is None:
        return None
    if not random_start or mode == "random":
        return mode
    return "random" if mode == "colmap" else f"{mode} (random at step 0)"


# Fields whose type the report relies on (bool is an int: a seed of `true` is refused by the check on str too).
# Fields written only where set: only final-set references have a source run, only runs with the floater guard on a count.
WRITTEN_WHEN_SET = ("final_set_of", "near_culled")

RESULT_TYPES = {"scene": str, "protocol": str, "selector": str, "seed": int, "test": Mapping, "timing": Mapping,
                "provenance": Mapping, "psnr_per_round": list, "test_views": list, "initial_views": list,
                "chosen_views": list}


def _from_v1(flat: Mapping[str, Any]) -> Dict[str, Any]:
    """A version-1 (flat) result as a version-2 object."""
    d = {**V1_DEFAULTS, **flat}
    memory = d["peak_memory_mb"] or {}
    timing = {k: d.get(k) for k in ("wall_seconds", "selection_seconds", "selection_seconds_per_round",
                                     "train_iter_ms_median", "train_total_seconds", "started_at", "sweep_id",
                                     "runs_per_gpu")}
    timing.update(peak_host_rss_mb=memory.get("host_rss"), peak_gpu_allocated_mb=memory.get("gpu_allocated"))
    old = dict(d["provenance"] or {})
    provenance = {"command": d["command"], "device": d["device"], "git_commit": old.pop("git_commit", None),
                  "libraries": old, "settings": d["settings"]}
    return {
        **{k: v for k, v in d.items() if k not in timing and k not in ("peak_memory_mb", "command", "device", "settings")},
        "timing": timing,
        "provenance": provenance,
        "data": data_from_command(d["command"]),
        "dataparser": (d["settings"] or {}).get("dataparser"),
        "test_views": [],
    }


def command_options(words: List[str]) -> Dict[str, str]:
    """`--flag value` and `--flag=value` in a recorded command's words: flag -> the word after it (the last where a flag
    repeats, as tyro reads it)."""
    flat = [part for w in words for part in (w.split("=", 1) if w.startswith("--") and "=" in w else [w])]
    return {flat[i]: flat[i + 1] for i in range(len(flat) - 1) if flat[i].startswith("--")}


def data_from_command(command: str) -> Optional[str]:
    """The `--data` folder of a recorded `ns-train` command (None without one)."""
    return command_options(shlex.split(command)).get("--data")


def load_results(out: Path) -> List[RunResult]:
    """Every run under a results folder (`<scene>/<protocol>/<selector>/seed*.json`), in path order."""
    return [RunResult.from_json(p) for p in sorted(Path(out).glob("*/*/*/seed*.json"))]


def load_final_sets(out: Path) -> List[RunResult]:
    """Every final-set reference under a results folder (`<scene>/<protocol>/<selector>/final-set/seed*.json`,
    beside the run it belongs to; `load_results` does not read them), in path order."""
    return [RunResult.from_json(p) for p in sorted(Path(out).glob("*/*/*/final-set/seed*.json"))]
