"""Two small fixes to nerfstudio's trainer that `hpgs` runs need, an optional final evaluation, and a schedule
restart.

- A resumed run (`--load-dir`) ends at the configured total step count; stock nerfstudio runs another full
  `max_num_iterations` after the checkpoint's step.
- Learning rates are saved as Python floats: splatfacto's exponential scheduler returns numpy float64, which
  ends up in the optimizer and scheduler state and makes `torch.load(weights_only=True)` (the default since
  torch 2.6) refuse the checkpoint in stock `ns-eval`, `ns-viewer` and resume.

`--final-eval-json PATH` writes what stock `ns-eval --output-path PATH` would write for the final checkpoint
(the same `get_average_eval_image_metrics(get_std=True)` call on the same weights), from the training process:
it saves `ns-eval`'s ~15 s of start-up per run, which `hpgs bench` pays hundreds of times.

`restart_schedules` makes every learning rate start over as if training began at the current step (the
datamanager's `reset-after-add`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Type

from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.schedulers import ExponentialDecayScheduler, ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from torch.optim import Optimizer, lr_scheduler

from hpgs_ns.atomic_write import write_json_atomic


@dataclass
class HpgsTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig; resumed runs stop at `max_num_iterations` in total."""

    _target: Type = field(default_factory=lambda: HpgsTrainer)
    final_eval_json: Optional[Path] = None
    """If set, evaluate the test views once training ends and write `ns-eval`'s JSON here."""


class HpgsTrainer(Trainer):
    """nerfstudio's Trainer whose resumed runs end at the configured total step count."""

    config: HpgsTrainerConfig

    def _load_checkpoint(self) -> None:
        super()._load_checkpoint()
        total = self.config.max_num_iterations
        if self._start_step > 0:
            self.config.max_num_iterations = max(total - self._start_step, 0)
            self.step = self._start_step - 1  # what `_after_train` saves if nothing is left to run

    def _after_train(self) -> None:
        # Before the parent's part: with the viewer on, it never returns.
        if self.config.final_eval_json is not None:
            write_final_eval(self, Path(self.config.final_eval_json))
        super()._after_train()


def write_final_eval(trainer: Trainer, path: Path) -> Path:
    """`ns-eval`'s output for the trainer's current weights (what `_after_train` saves as the final checkpoint)."""
    metrics = trainer.pipeline.get_average_eval_image_metrics(step=trainer.step, get_std=True)
    payload = {
        "experiment_name": trainer.config.experiment_name,
        "method_name": trainer.config.method_name,
        "checkpoint": str(trainer.checkpoint_dir / f"step-{trainer.step:09d}.ckpt"),
        "results": metrics,
    }
    return write_json_atomic(path, payload)


@dataclass
class FloatExponentialDecaySchedulerConfig(ExponentialDecaySchedulerConfig):
    """nerfstudio's exponential decay with warm-up, computed in Python floats (checkpoint-safe)."""

    _target: Type = field(default_factory=lambda: FloatExponentialDecayScheduler)


class FloatExponentialDecayScheduler(ExponentialDecayScheduler):
    """Same schedule as `ExponentialDecayScheduler`; the multiplier is a Python float, never numpy."""

    config: FloatExponentialDecaySchedulerConfig

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> lr_scheduler.LRScheduler:
        cfg = self.config
        lr_final = lr_init if cfg.lr_final is None else cfg.lr_final

        def multiplier(step: int) -> float:
            if step < cfg.warmup_steps:
                frac = min(max(step / cfg.warmup_steps, 0.0), 1.0)
                ramp = math.sin(0.5 * math.pi * frac) if cfg.ramp == "cosine" else frac
                lr = cfg.lr_pre_warmup + (lr_init - cfg.lr_pre_warmup) * ramp
            else:
                t = min(max((step - cfg.warmup_steps) / (cfg.max_steps - cfg.warmup_steps), 0.0), 1.0)
                lr = math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)
            return float(lr / lr_init)

        return lr_scheduler.LambdaLR(optimizer, lr_lambda=multiplier)


def restart_schedules(optimizers: Optimizers) -> None:
    """Restart every learning-rate schedule from its first step.

    nerfstudio steps its schedulers once per iteration without a step argument, so a scheduler's own counter
    (`last_epoch`) is the position in the schedule; setting it back restarts warm-up and decay, and being part
    of the scheduler's state_dict it is saved in checkpoints and restored by `--load-dir`."""
    for scheduler in optimizers.schedulers.values():
        scheduler.last_epoch = -1
        scheduler.step()  # -> last_epoch 0, every group's lr = initial lr x schedule(0)
