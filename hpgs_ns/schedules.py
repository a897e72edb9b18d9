"""Learning-rate schedules for `hpgs` runs: splatfacto's exponential decay in Python floats, and a restart.

`FloatExponentialDecayScheduler` is nerfstudio's `ExponentialDecayScheduler` computed in Python floats:
splatfacto's scheduler returns numpy float64, which ends up in the optimizer and scheduler state and makes
`torch.load(weights_only=True)` (the default since torch 2.6) refuse the checkpoint in stock `ns-eval`,
`ns-viewer` and resume.

`restart_schedules` makes every learning rate start over as if training began at the current step (the
selection rounds' `reset-after-add`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Type

from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.schedulers import ExponentialDecayScheduler, ExponentialDecaySchedulerConfig
from torch.optim import Optimizer, lr_scheduler


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
