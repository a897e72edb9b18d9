"""When things happen in a run: the round steps, and the run's last step after a resume.

One rule for "is `step` a round step" (select-at, or a positive multiple of select-every), used by the rounds,
their plan, eval-each-round and (with its own period) the snapshots.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence


@dataclass(frozen=True)
class Every:
    """Steps `period`, 2 `period`, ... (never step 0); `at`, when given, replaces them."""

    period: int
    at: Sequence[int] = ()

    def __contains__(self, step: int) -> bool:
        if self.at:
            return step in self.at
        return step > 0 and self.period > 0 and step % self.period == 0

    def between(self, first: int, end: int) -> List[int]:
        """The scheduled steps in [first, end), in order."""
        if self.at:
            return sorted(s for s in set(self.at) if first <= s < end and s > 0)
        if self.period <= 0:
            return []
        start = max(self.period, -(-first // self.period) * self.period)
        return list(range(start, end, self.period))


def run_steps(trainer) -> tuple:
    """(first step, end step) of what this process trains: steps [first, end), both absolute.

    nerfstudio's trainer runs `max_num_iterations` more steps after the step a run resumes from (`--load-dir`);
    `HpgsTrainer` rewrites that to the steps left and keeps the run's total as `end_step`, so both are read here,
    once, instead of from `max_num_iterations`."""
    first = int(getattr(trainer, "start_step", getattr(trainer, "_start_step", 0)))
    end = getattr(trainer, "end_step", None)
    if end is None:
        end = first + int(trainer.config.max_num_iterations)
    return first, int(end)
