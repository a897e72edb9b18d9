"""Learning-rate schedules for `hpgs` runs: splatfacto's exponential decay in Python floats, and a restart.

`FloatExponentialDecayScheduler` is nerfstudio's `ExponentialDecayScheduler` computed in Python floats:
splatfacto's scheduler returns numpy float64, which ends up in the optimizer and scheduler state and makes
`torch.load(weights_only=True)` (the default since torch 2.6) refuse the checkpoint in stock `ns-eval`,
`ns-viewer` and resume.

`restart_schedules` makes every learning rate start over as if training began at the current step (the
restarts' `every-round`), optionally squeezed into the steps a run has left (a restart at a view count).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Type

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
        return lr_scheduler.LambdaLR(optimizer, lr_lambda=DecayMultiplier(
            lr_init=lr_init, lr_final=lr_init if cfg.lr_final is None else cfg.lr_final, lr_pre_warmup=cfg.lr_pre_warmup,
            warmup_steps=cfg.warmup_steps, max_steps=cfg.max_steps, cosine=cfg.ramp == "cosine"))


@dataclass
class DecayMultiplier:
    """lr(step) / lr_init for nerfstudio's warm-up + exponential decay, with the step multiplied by `speed`.

    A callable object, not a closure: LambdaLR saves its `__dict__` in the scheduler's state_dict, so a schedule
    squeezed by a restart (`speed` > 1) is squeezed again after `--load-dir`."""

    lr_init: float
    lr_final: float
    lr_pre_warmup: float
    warmup_steps: int
    max_steps: int
    cosine: bool = False
    speed: float = 1.0

    def __call__(self, step: int) -> float:
        step = step * self.speed
        if step < self.warmup_steps:
            frac = min(max(step / self.warmup_steps, 0.0), 1.0)
            ramp = math.sin(0.5 * math.pi * frac) if self.cosine else frac
            lr = self.lr_pre_warmup + (self.lr_init - self.lr_pre_warmup) * ramp
        else:
            span = self.max_steps - self.warmup_steps
            t = min(max((step - self.warmup_steps) / span, 0.0), 1.0) if span > 0 else 0.0
            lr = math.exp(math.log(self.lr_init) * (1 - t) + math.log(self.lr_final) * t)
        return float(lr / self.lr_init)


def restart_schedules(optimizers: Optimizers, span: Optional[int] = None) -> None:
    """Restart every learning-rate schedule from its first step; with `span`, the whole schedule (warm-up and
    decay to its final rate) then runs in `span` steps.

    nerfstudio steps its schedulers once per iteration without a step argument, so a scheduler's own counter
    (`last_epoch`) is the position in the schedule; setting it back restarts warm-up and decay, and being part
    of the scheduler's state_dict it is saved in checkpoints and restored by `--load-dir`."""
    for scheduler in optimizers.schedulers.values():
        if span is not None:
            for multiplier in getattr(scheduler, "lr_lambdas", ()):
                if isinstance(multiplier, DecayMultiplier):
                    multiplier.speed = max(multiplier.max_steps / max(int(span), 1), 1.0)
        scheduler.last_epoch = -1
        scheduler.step()  # -> last_epoch 0, every group's lr = initial lr x schedule(0)
