"""nerfstudio's trainer with what `hpgs` runs need: resumes that continue training, checkpoints that are never
half-written, and an optional final evaluation.

- A resumed run (`--load-dir`, `--load-checkpoint`) ends at the configured total step count (stock nerfstudio runs
  another full `max_num_iterations` after the checkpoint's step), and trains: splatfacto's `load_state_dict`
  replaces the Gaussian parameters with new tensors, which stock nerfstudio's optimizers (built before the load)
  never see, so a stock resume silently stops training and crashes at its first densification. Here the optimizers
  are rebound to the loaded parameters before their state is loaded.
- Checkpoints are written to a temp file and renamed; `--load-dir` skips (with one line) a checkpoint that does not
  load, and a resume whose selection options differ from the checkpoint's is refused with one line.
- A config.yml written by hpgs-ns 0.1 (a VanillaPipeline, rounds inside the datamanager) is upgraded to the
  `hpgs` pipeline when it is trained again (`--load-config`), so its selection rounds still run.

`--final-eval-json PATH` writes what stock `ns-eval --output-path PATH` would write for the final checkpoint
(the same `get_average_eval_image_metrics(get_std=True)` call on the same weights) and each test view's metrics,
from the training process: it saves `ns-eval`'s ~15 s of start-up per run, which `hpgs bench` pays hundreds of times.
"""

from __future__ import annotations

import copy
import functools
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Type

import torch
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns import compat, schedules
from hpgs_ns.atomic_write import atomic_path, write_json_atomic
from hpgs_ns.compat import upgrade_pipeline_config
from hpgs_ns.errors import OptionError, UserError
from hpgs_ns.pipeline import HpgsPipelineConfig

# config.yml files of hpgs-ns 0.1 name the scheduler classes here (the other old-run rules: hpgs_ns.compat).
FloatExponentialDecaySchedulerConfig = schedules.FloatExponentialDecaySchedulerConfig
FloatExponentialDecayScheduler = schedules.FloatExponentialDecayScheduler


@dataclass
class HpgsTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig; resumed runs stop at `max_num_iterations` in total."""

    _target: Type = field(default_factory=lambda: HpgsTrainer)
    final_eval_json: Optional[Path] = None
    """If set, evaluate the test views once training ends and write `ns-eval`'s JSON here."""
    final_eval_worst_views: int = 2
    """With `--final-eval-json`, also save the lowest-PSNR test views as JPEGs beside it (ground truth | render),
    named in the JSON's `worst_views`: one view can move a scene's mean by a dB (a floater), and the checkpoint
    often stays on the GPU machine. 0: none."""
    schedules_follow_steps: bool = True
    """Size every learning-rate schedule (its decay to the final rate) to `--max-num-iterations`, whatever
    `--optimizers.*.scheduler.max-steps` says: a 20000-step run otherwise trains its last 5000 steps, and every view
    added in them, at the floor rate of the 15000-step default. False: the schedules' own max-steps (hpgs-ns <= 0.3)."""

    def __post_init__(self) -> None:
        if self.final_eval_worst_views < 0:
            raise OptionError(f"--final-eval-worst-views {self.final_eval_worst_views}: the number of views to save "
                              "must be >= 0 (0: none)")
        follow_run_length(self)
        # tyro builds this config while it parses the command line: a --data that names a file or nothing is a
        # one-line error before nerfstudio prints anything or makes a run folder. (A config.yml skips __init__.)
        if self.data is not None:
            from hpgs_ns.dataparser import SceneDataError, check_data_path

            try:
                check_data_path(Path(self.data))
            except SceneDataError as err:  # a ValueError, which tyro would draw in a box of its own
                raise OptionError(str(err)) from None

    def print_to_terminal(self) -> None:
        """One line instead of nerfstudio's ~320-line config dump (the whole config is the run's config.yml)."""
        pipeline = self.pipeline
        selection = getattr(pipeline, "selection", None)
        what = f"selector {selection.selector}, " if selection is not None else ""
        CONSOLE.print(f"hpgs: {what}{self.max_num_iterations} steps, data {pipeline.datamanager.data}; "
                      f"the full config: {self.get_base_dir() / 'config.yml'}", soft_wrap=True)


def follow_run_length(config: TrainerConfig) -> None:
    """`schedules_follow_steps`: every scheduler's max-steps set to the run's total steps (on a copy of the optimizer
    configs, which tyro shares with the method's default config). Runs at parse time, so config.yml shows the
    schedule that trains, and again when the trainer starts (configs built in Python may change the steps after)."""
    # vars(): a config.yml of hpgs-ns <= 0.3 has no such field and keeps the schedule it trained with.
    if not vars(config).get("schedules_follow_steps", False) or config.max_num_iterations is None:
        return
    optimizers = copy.deepcopy(config.optimizers)
    for groups in optimizers.values():
        scheduler = groups.get("scheduler") if isinstance(groups, dict) else None
        if scheduler is not None and hasattr(scheduler, "max_steps"):
            scheduler.max_steps = int(config.max_num_iterations)
    config.optimizers = optimizers


class HpgsTrainer(Trainer):
    """nerfstudio's Trainer whose resumed runs end at the configured total step count."""

    config: HpgsTrainerConfig

    def __init__(self, config: HpgsTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        if upgrade_pipeline_config(config, HpgsPipelineConfig):
            CONSOLE.print("config.yml of hpgs-ns 0.1: its pipeline is now the hpgs pipeline (selection rounds run)")
        follow_run_length(config)  # before set-up builds the schedulers; a resume keeps the total step count
        from unittest import mock

        import nerfstudio.engine.trainer as stock

        # nerfstudio builds `torch.cuda.amp.GradScaler`, deprecated (a FutureWarning in every run); the same scaler
        # under its current name, built here instead (same state_dict, so checkpoints are unchanged)
        with mock.patch.object(stock, "GradScaler", functools.partial(torch.amp.GradScaler, "cuda")):
            super().__init__(config, local_rank, world_size)
        self.end_step = int(config.max_num_iterations)
        """The run's last step + 1, counted from step 0 (`max_num_iterations` is rewritten on resume)."""

    @property
    def start_step(self) -> int:
        """The first step this process trains: 0, or the step after the checkpoint it resumed from."""
        return int(self._start_step)

    def setup(self, test_mode: str = "val") -> None:
        """nerfstudio's set-up; one that fails (a bad scene, a bad checkpoint) removes the run folder ns-train made
        for it just before, if that holds nothing but this run's config.yml, so the error is all that is left."""
        import contextlib

        import yaml

        from hpgs_ns.atomic_write import removed_on_failure

        own = {"config.yml": yaml.dump(self.config)}  # what ns-train's `save_config` wrote
        cleanup = removed_on_failure(self.base_dir, own, stop_at=self.config.output_dir) if self.local_rank == 0 \
            else contextlib.nullcontext()
        datamanager = self.config.pipeline.datamanager
        with cleanup:
            # read before the pipeline is built: a checkpoint that holds how its splat started (0.4 on) spares the
            # datamanager rebuilding that start (`seed-points active` triangulates the initial views) for nothing
            self._checkpoint = self._read_checkpoint()
            start_saved = self._checkpoint[1] is not None and saves_model_start(self._checkpoint[1])
            try:
                if start_saved and hasattr(datamanager, "seed_points"):
                    datamanager.start_from_checkpoint = True  # not a field: never in config.yml
                super().setup(test_mode=test_mode)
            finally:
                vars(datamanager).pop("start_from_checkpoint", None)
                self._checkpoint = None  # the state is the pipeline's and optimizers' now

    def _load_checkpoint(self) -> None:
        path, loaded = getattr(self, "_checkpoint", None) or self._read_checkpoint()
        if loaded is None:
            CONSOLE.print("No Nerfstudio checkpoint to load, so training from scratch.")
            return
        step = int(loaded["step"])
        self._start_step = step + 1
        sizes = schedule_sizes(self.optimizers)  # as configured for this run, before the checkpoint's replace them
        try:
            self.pipeline.load_pipeline(loaded["pipeline"], step)
            check_resume_matches(self.pipeline)
            # splatfacto's load_state_dict made new parameter tensors: point the optimizers at them, then load their
            # state (Adam's moments and step counts land on the parameters the model trains).
            rebind_optimizers(self.optimizers, self.pipeline.get_param_groups())
            self.optimizers.load_optimizers(loaded["optimizers"])
            if "schedulers" in loaded and self.config.load_scheduler:
                self.optimizers.load_schedulers(loaded["schedulers"])
            self.grad_scaler.load_state_dict(loaded["scalers"])
        except UserError:
            raise
        except (RuntimeError, KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
            detail = str(err).strip().splitlines()[0][:160] if str(err).strip() else "no detail"
            raise CheckpointError(f"{path} does not fit this run ({type(err).__name__}: {detail}); resume with the "
                                  "options it was trained with, or start a new run without --load-dir") from err
        resized = resize_loaded_schedules(self.optimizers, sizes)
        if resized:
            old, new = resized
            CONSOLE.print(f"--max-num-iterations {self.end_step}: the learning-rate schedules now end at step {new} (the "
                          f"checkpoint's ended at step {old}), continuing from step {self._start_step}", soft_wrap=True)
        if "random_state" in loaded:
            set_random_state(loaded["random_state"])
        model = self.pipeline.model
        if hasattr(model, "step_offset"):  # splatfacto's load_state_dict leaves its step at 30000
            model.step = self._start_step - int(model.step_offset)
        follow_restart_clock(model, self.end_step)
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")
        # nerfstudio's loop runs max_num_iterations steps after the checkpoint: make that the steps left.
        self.config.max_num_iterations = max(self.end_step - self._start_step, 0)
        self.step = self._start_step - 1  # what `_after_train` saves if nothing is left to run

    def _read_checkpoint(self):
        """(path, state) of the checkpoint to resume from, or (None, None). With `--load-dir` and no
        `--load-step`, the newest checkpoint that loads: one that does not (a kill mid-save under stock
        nerfstudio) is skipped with one line."""
        load_dir, named = self.config.load_dir, self.config.load_checkpoint
        if load_dir is None and named is None:
            return None, None
        if load_dir is not None and self.config.load_step is None:
            load_dir = Path(load_dir)
            if not load_dir.is_dir():
                raise CheckpointError(f"--load-dir {load_dir} is not a folder; pass the run's nerfstudio_models folder")
            paths = sorted(load_dir.glob("step-*.ckpt"), key=checkpoint_step, reverse=True)
            for path in paths:
                try:
                    return path, load_checkpoint_file(path)
                except CheckpointError as err:
                    CONSOLE.print(f"[yellow]skipping {path.name}: {err}", soft_wrap=True)
            raise CheckpointError(f"--load-dir {load_dir} holds no checkpoint that loads (step-*.ckpt); "
                                  "start a new run without --load-dir")
        path = Path(named) if load_dir is None else Path(load_dir) / f"step-{self.config.load_step:09d}.ckpt"
        return path, load_checkpoint_file(path)

    def save_checkpoint(self, step: int) -> None:
        """nerfstudio's checkpoint, written to a temp file beside the checkpoint folder and renamed, so a kill
        mid-save never leaves a truncated `step-*.ckpt` for `--load-dir`, `ns-eval` or `ns-viewer` to pick."""
        if not comms.is_main_process():
            return
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        state = {
            "step": step,
            "pipeline": pipeline.state_dict(),
            "optimizers": {k: v.state_dict() for k, v in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for k, v in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
            # Not in stock checkpoints: a resumed run draws the same random backgrounds as an uninterrupted one.
            "random_state": random_state(),
        }
        # The temp file sits in the run folder, not the checkpoint folder: nerfstudio parses every name there.
        tmp = self.checkpoint_dir.parent / f".{path.name}.{os.getpid()}.tmp"
        for stale in self.checkpoint_dir.parent.glob(".step-*.ckpt.*.tmp"):
            stale.unlink(missing_ok=True)  # left by a run killed mid-save
        try:
            torch.save(state, tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        if self.config.save_only_latest_checkpoint:
            for other in self.checkpoint_dir.glob("*.ckpt"):
                if other != path:
                    other.unlink()

    def train_iteration(self, step: int):
        """nerfstudio's iteration; the loss and metric dicts it returns for logging are detached (their backward is
        done), so its writer's `float()` raises no "Converting a tensor with requires_grad=True" warning."""
        loss, loss_dict, metrics_dict = super().train_iteration(step)
        detach = lambda d: {k: v.detach() if isinstance(v, torch.Tensor) else v for k, v in d.items()}  # noqa: E731
        return loss.detach() if isinstance(loss, torch.Tensor) else loss, detach(loss_dict), detach(metrics_dict)

    def _after_train(self) -> None:
        # Before the parent's part: with the viewer on, it never returns.
        if self.config.final_eval_json is not None:
            rng = random_state()
            write_final_eval(self, Path(self.config.final_eval_json), worst_views=self.config.final_eval_worst_views)
            set_random_state(rng)  # the final checkpoint resumes as if no evaluation had run
        super()._after_train()


def saves_model_start(state: Dict[str, Any]) -> bool:
    """Whether a checkpoint's model state says how its splat started (`random_start`, hpgs-ns 0.4 on)."""
    extra = state.get("pipeline", {}).get("_model._extra_state")
    return isinstance(extra, dict) and "random_start" in extra


class CheckpointError(UserError, RuntimeError):
    """A checkpoint cannot be resumed from."""


def checkpoint_step(path: Path) -> int:
    """The step in a nerfstudio checkpoint's name (`step-000001234.ckpt` -> 1234; -1 if none)."""
    digits = path.stem.partition("-")[2]
    return int(digits) if digits.isdigit() else -1


def load_checkpoint_file(path: Path) -> Dict[str, Any]:
    """A checkpoint's state (on the CPU), or CheckpointError naming why it cannot be read."""
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist; pass one of the run's nerfstudio_models/step-*.ckpt")
    try:
        state = torch.load(path, map_location="cpu")
    except Exception as err:  # truncated zip, unpickling error, ...: all mean the same to the user
        detail = f"{type(err).__name__}: {str(err).splitlines()[0][:120]}" if str(err).strip() else type(err).__name__
        raise CheckpointError(f"{path} does not load ({detail}); it is probably truncated") from err
    if not isinstance(state, dict) or not {"step", "pipeline", "optimizers"} <= set(state):
        raise CheckpointError(f"{path} is not a nerfstudio checkpoint (no step, pipeline and optimizers)")
    step = state["step"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0 or not all(
            isinstance(state.get(key, {}), dict) for key in ("pipeline", "optimizers", "schedulers", "scalers")):
        raise CheckpointError(f"{path} is not a nerfstudio checkpoint (its step, pipeline, optimizers, schedulers or "
                              "scalers are of the wrong type); pass another step-*.ckpt of the run")
    return state


def random_state() -> Dict[str, Any]:
    """The process's random streams (torch, CUDA, Python, numpy) as tensors and plain types (weights_only-safe)."""
    import random

    import numpy as np

    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "python": random.getstate(), "numpy": [str(kind), torch.from_numpy(keys.astype("int64")), int(pos),
                                                    int(has_gauss), float(cached)]}


def set_random_state(state: Dict[str, Any]) -> None:
    import random

    import numpy as np

    torch.set_rng_state(state["torch"])
    if state.get("cuda") and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(state["cuda"])
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype("uint32"), pos, has_gauss, cached))


def schedule_sizes(optimizers) -> Dict[str, List[int]]:
    """Each scheduler's decay lengths (`DecayMultiplier.max_steps`, one per parameter group), by optimizer name."""
    return {name: [m.max_steps for m in getattr(scheduler, "lr_lambdas", ()) if isinstance(m, schedules.DecayMultiplier)]
            for name, scheduler in optimizers.schedulers.items()}


def resize_loaded_schedules(optimizers, sizes: Dict[str, List[int]]) -> Optional[tuple]:
    """After a resume: the schedules restored from the checkpoint (LambdaLR's state keeps its multiplier, sized to
    the run the checkpoint was saved in) are re-sized to `sizes` (this run's, from `--max-num-iterations`), so an
    extended run follows the schedule of an uninterrupted run of its length from the loaded step on; the current
    learning rates move to it at once. A schedule squeezed by a restart (`restarts`) keeps its start and now ends at
    the new last step, as the uninterrupted run's restart squeezed it. Returns (old, new) decay length of the first
    schedule changed, or None."""
    changed = None
    for name, scheduler in optimizers.schedulers.items():
        multipliers = [m for m in getattr(scheduler, "lr_lambdas", ()) if isinstance(m, schedules.DecayMultiplier)]
        wanted = sizes.get(name, [])
        if len(multipliers) != len(wanted):
            continue
        moved = False
        for multiplier, size in zip(multipliers, wanted):
            if multiplier.max_steps != size and multiplier.max_steps > 0:
                changed = changed or (multiplier.max_steps, size)
                if multiplier.speed != 1.0:
                    # squeezed into the steps a restart had left (`restart_schedules`): the steps after it grow by
                    # what the run grew by, so it ends with the run, as the longer run's restart made it
                    span = round(multiplier.max_steps / multiplier.speed) + size - multiplier.max_steps
                    multiplier.speed = max(size / max(span, 1), 1.0)
                multiplier.max_steps, moved = size, True
        if moved:
            for group, base, fn in zip(scheduler.optimizer.param_groups, scheduler.base_lrs, scheduler.lr_lambdas):
                group["lr"] = base * fn(scheduler.last_epoch)
    return changed


def follow_restart_clock(model, end_step: int) -> None:
    """After a resume: a model whose restart squeezed its step-keyed schedule into the steps the run had left
    (`clock_scale` < 1, from the restart's step `step_offset`) squeezes it into the steps this run has left, as the
    restart of an uninterrupted run of `end_step` steps did (`strategies.restarts.Restarts.reset`); a resume that extends
    the run otherwise densifies on the old run's clock."""
    scale, restart = float(getattr(model, "clock_scale", 1.0)), int(getattr(model, "step_offset", 0))
    if scale != 1.0 and 0 < restart and hasattr(model, "set_clock_scale"):
        model.set_clock_scale(max(int(end_step) - restart, 1) / max(int(end_step), 1))


def rebind_optimizers(optimizers, param_groups: Dict[str, List[torch.nn.Parameter]]) -> None:
    """Make each optimizer (one per parameter group, as nerfstudio builds them) hold the group's current parameter
    tensors, moving any state it already has onto them."""
    for name, optimizer in optimizers.optimizers.items():
        params = list(param_groups.get(name, []))
        group = optimizer.param_groups[0]
        if len(optimizer.param_groups) != 1 or len(group["params"]) != len(params):
            continue  # not a one-group-per-name optimizer: leave it as nerfstudio built it
        for old, new in zip(group["params"], params):
            if old is not new and old in optimizer.state:
                optimizer.state[new] = optimizer.state.pop(old)
        group["params"] = params
        optimizers.parameters[name] = params


def check_resume_matches(pipeline) -> None:
    """Refuse (one line) a resume whose selection options differ from those the checkpoint was trained with: the
    round log would mix two selectors' or schedules' choices."""
    datamanager = pipeline.datamanager
    saved = getattr(datamanager, "loaded_selection_signature", None)
    now = getattr(datamanager, "selection_signature", None)
    if not saved or not now:
        return  # a checkpoint written before 0.3, or not an hpgs pipeline
    if "seed-points" not in saved and "seed-points" in now:
        # written since `auto`: an older checkpoint's start shows only in whether it has active starts' key (0.4's);
        # without it, a start other than active is taken as unchanged and an active one left to differ
        if "after-add.restart-active-starts" in saved:
            saved = {**saved, "seed-points": "active"}
        elif now["seed-points"] != "active":
            saved = {**saved, "seed-points": now["seed-points"]}
    removed = compat.removed_options(saved)
    if removed:
        raise CheckpointError(f"this checkpoint was trained with {' and '.join(removed)}, which hpgs-ns 0.5 removed; "
                              "resume it with hpgs-ns 0.4, the version that wrote it, or start a new run without --load-dir")
    saved = compat.fill_added_signature_keys(compat.seeded_restarts_key(saved, now), now)
    changed = [key for key in sorted(set(saved) | set(now)) if saved.get(key) != now.get(key)]
    if "selector" in changed:  # another selector's options are not a change of their own
        selectors = {saved.get("selector"), now.get("selector"), saved.get("shortlist"), now.get("shortlist")} - {None}
        changed = [k for k in changed if k.partition(".")[0] not in selectors or (k in saved and k in now)]
    if changed:
        def shown(signature: Dict[str, str], key: str) -> str:
            return signature.get(key, "off" if key == "near-cull" else "(unset)")  # the guard's key exists only when on

        diff = "; ".join(f"{key}: checkpoint {shown(saved, key)}, now {shown(now, key)}" for key in changed)
        hint = (" (--pipeline.datamanager.seed-points as it was trained: the default was colmap before auto)"
                if "seed-points" in changed else "")
        if "selector" in changed and saved.get("selector"):
            hint += (f" (--pipeline.selection.selector {saved['selector']}"
                     + (": the default was hpgs before farthest" if saved["selector"] == "hpgs" else "") + ")")
        if "near-cull" in changed:
            hint += f" ({compat.near_cull_flags(saved.get('near-cull'))})"
        for key in (k for k in changed if k == "reset-after-add" or k.startswith("after-add")):
            hint += f" ({compat.restart_flags(key, saved.get(key))}"
            hint += ": seeded starts did not restart before)" if key == compat.SEEDED_RESTARTS and saved.get(key) == "False" else ")"
        raise CheckpointError(f"this resume changes what the checkpoint was trained with ({diff}); resume with the "
                              f"checkpoint's options{hint}, or start a new run without --load-dir")


def write_final_eval(trainer: Trainer, path: Path, worst_views: int = 0) -> Path:
    """`ns-eval`'s output for the trainer's current weights (what `_after_train` saves as the final checkpoint),
    plus each test view's own metrics (`test_views`: name, psnr, ssim, lpips, `view_depths`'s two depths and, from
    the hpgs model, what lies in front of its camera (`render.front.describe_front`), in the test split's order) and, with
    `worst_views`, JPEGs of the lowest-PSNR views beside `path` (`worst_views`: name, psnr, image file name), and
    the splat's size (`num_gaussians`) and what its strategies record (the floater guard's `near_culled`)."""
    pipeline = trainer.pipeline
    model = pipeline.model
    per_view: List[Dict[str, float]] = []
    worst: List[tuple] = []  # (psnr, index, image), the `worst_views` lowest so far
    score_view = model.get_image_metrics_and_images

    def recording(outputs, batch):
        metrics_dict, images = score_view(outputs, batch)
        per_view.append({**{k: float(v) for k, v in metrics_dict.items()}, **view_depths(outputs)})
        if worst_views > 0 and "img" in images and "psnr" in metrics_dict:
            worst.append((float(metrics_dict["psnr"]), len(per_view) - 1, images["img"].detach().cpu()))
            worst.sort(key=lambda item: item[0])
            del worst[worst_views:]
        return metrics_dict, images

    # nerfstudio averages the views' metrics without returning them: record each as it is scored (this call only).
    model.get_image_metrics_and_images = recording
    try:
        metrics = pipeline.get_average_eval_image_metrics(step=trainer.step, get_std=True)
    finally:
        del model.get_image_metrics_and_images
    names = list(getattr(pipeline.datamanager, "test_view_names", []))
    named = len(names) == len(per_view)
    test_views = [{"name": n, **m} for n, m in zip(names, per_view)] if named else []
    if test_views and hasattr(model, "strategies_by_name"):  # the hpgs model
        from hpgs_ns.render.front import describe_front

        dm = pipeline.datamanager
        # the views it trained on, not the candidates
        training = dm.active_cameras if hasattr(dm, "active_cameras") else dm.train_dataset.cameras
        fronts = describe_front(model, dm.eval_dataset.cameras, training, split=dm.train_dataset.cameras)
        test_views = [{**v, **f} for v, f in zip(test_views, fronts)]
    worst_saved = []
    for rank, (psnr, index, image) in enumerate(worst):
        file = path.with_name(f"{path.stem}-worst{rank}.jpg")
        save_jpeg(image, file)
        worst_saved.append({"name": names[index] if named else str(index), "psnr": psnr, "image": file.name})
    payload = {
        "experiment_name": trainer.config.experiment_name,
        "method_name": trainer.config.method_name,
        "checkpoint": str(trainer.checkpoint_dir / f"step-{trainer.step:09d}.ckpt"),
        "results": metrics,
        "test_views": test_views,
        "worst_views": worst_saved,
        "num_gaussians": int(getattr(model, "num_points", 0)),
    }
    for strategy in getattr(model, "trainer_strategies", []):  # e.g. the floater guard's count, where it was on
        payload.update(strategy.final_eval())
    return write_json_atomic(path, payload)


def view_depths(outputs: Dict[str, Any]) -> Dict[str, Optional[float]]:
    """The 10th percentile and median of a render's depth over its opaque pixels (accumulation >= 0.5), in the
    splat's units: a view that fails because Gaussians float just in front of its camera shows a near 10th
    percentile that a replicate of the same run does not. None where the render has no depth or no opaque pixel."""
    depth, alpha = outputs.get("depth"), outputs.get("accumulation")
    if depth is None or alpha is None:
        return {"depth_p10": None, "depth_median": None}
    values = depth.detach().reshape(-1)[alpha.detach().reshape(-1) >= 0.5].float().sort().values
    if values.numel() == 0:
        return {"depth_p10": None, "depth_median": None}
    return {"depth_p10": float(values[int(0.1 * (values.numel() - 1))]),
            "depth_median": float(values[(values.numel() - 1) // 2])}


def save_jpeg(image: torch.Tensor, path: Path) -> Path:
    """An [H, W, 3] (or [1, 3, H, W]) image in [0, 1] as a JPEG, written to a temp file then renamed."""
    from PIL import Image

    if image.dim() == 4:
        image = image[0].permute(1, 2, 0)
    pixels = (image.clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    with atomic_path(path, suffix=".jpg") as tmp:
        Image.fromarray(pixels).save(tmp, quality=90)
    return path
