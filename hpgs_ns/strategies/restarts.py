"""Restarts: the splat starts over as rounds add views (`--pipeline.model.restarts.*`).

splatfacto keys everything to step 0: the means' learning rate decays to its floor, densification stops at
`stop-split-at` and opacity resets come every `reset-alpha-every` refines. A view added late meets a splat that can
no longer move, grow or drop what the first few views built from too little evidence. A restart at set view counts
drops that and trains the views present then together, as from step 0, in the steps left; every start restarts at
twice and four times its initial view count by default (FisherRF's 4 views: at 8 and 16; HP-GS's 20 + 7: never).
`every-round` is FisherRF's own protocol (Jiang et al., ECCV 2024): the splat goes back to step 0 after every round
and the schedules run again in full from that step.

The model provides the mechanics (`reset_to_initial`, a step-keyed clock `set_clock_scale`, `replace_gaussians`);
this strategy decides when, and records each restart as a `RestartOutcome`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Tuple, Type

from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns.errors import OptionError
from hpgs_ns.schedules import restart_schedules
from hpgs_ns.strategies.base import PointsOutcome, RoundAdded, RoundsPlan, RunStart, Strategy, StrategyConfig

FLAG = "--pipeline.model.restarts."


class RestartError(OptionError):
    """A restart option value that makes no sense, or a restart that cannot run."""


@dataclass
class RestartsConfig(StrategyConfig):
    """When the splat starts over as rounds add views (see `hpgs_ns.strategies.restarts`)."""

    _target: Type = field(default_factory=lambda: Restarts)
    every_round: bool = False
    """After each round, start training over from the new view set, as FisherRF (Jiang et al., ECCV 2024) does:
    the Gaussians go back to the step-0 ones, optimizer moments, densification state and camera optimizer are
    cleared, and learning rates and splatfacto's step-keyed schedule (densification, opacity reset, SH degree,
    resolution) restart at the round's step. The trainer's step keeps counting; the run ends at
    max-num-iterations. The view-count restarts below do not run with it."""
    at_views: Tuple[int, ...] = ()
    """Start the splat over when a round brings the number of training views to each of these counts (e.g. 8 16):
    the Gaussians go back to their step-0 state, and the learning-rate schedules and splatfacto's step-keyed
    schedule (densification, opacity resets, SH degree, resolution) run again, squeezed into the steps left. What
    the first few views built from too little evidence (floaters in front of views that came later) is dropped;
    the views then train together, as they would from step 0. Empty: see random-starts, active-starts and
    seeded-starts."""
    random_starts: bool = True
    """When at-views is empty, a splat that started from random points (seed-points colmap without a point cloud,
    random-init or seed-points random) restarts at twice and four times the initial view count (FisherRF's 4 views:
    at 8 and 16; HP-GS's 20 + 7: never). Random starts lock in what the first views built; seeded ones barely do
    (docs/active-training.md). False: never restart unless at-views says so."""
    active_starts: bool = True
    """When at-views is empty, a splat seeded by `seed-points active` restarts too, at twice and four times the
    initial view count, from the points all active views triangulate then: a few initial views triangulate
    hundreds of points, the final views thousands, and what the splat grew from the first is locked in as a random
    start's is (docs/active-training.md). False: an active start that found enough points never restarts."""
    seeded_starts: bool = True
    """When at-views is empty, a splat seeded by the capture's points (seed-points colmap or colmap-initial, or auto
    where the capture has a point cloud) restarts too, at twice and four times the initial view count, from those
    points: the views present then train together as from step 0, so the order the views came in costs little
    (docs/active-training.md). False: such a splat never restarts unless at-views says so."""

    def __post_init__(self) -> None:
        self.at_views = tuple(int(n) for n in self.at_views)
        if any(n < 1 for n in self.at_views):
            raise RestartError(f"{FLAG}at-views {' '.join(map(str, self.at_views))}: view counts must be >= 1")

    def restart_counts(self, initial_views: int, random_start: bool, active_start: bool = False,
                       final_views: Optional[int] = None) -> Tuple[int, ...]:
        """The view counts at which the splat restarts, for a run of `initial_views` initial views that started from
        random points (`random_start`), from the initial views' triangulation (`active_start`) or, neither, from the
        capture's points, and that ends with `final_views` (counts beyond it never come). None under every-round."""
        if self.every_round:
            return ()
        counts: Tuple[int, ...] = ()
        seeded_start = not random_start and not active_start
        if self.at_views:
            counts = self.at_views
        elif ((self.random_starts and random_start) or (self.active_starts and active_start)
              or (self.seeded_starts and seeded_start)):
            counts = (2 * initial_views, 4 * initial_views)  # FisherRF's 4 views: 8 and 16
        if final_views is not None:
            counts = tuple(n for n in counts if initial_views < n <= final_views)
        return tuple(sorted(set(counts)))

    def signature(self, seed_points: str, random_start: bool) -> Dict[str, str]:
        """What a resumed run must keep, under the keys checkpoints have always held (`hpgs_ns.compat` reads older
        ones): `reset-after-add`, `after-add` (the view-count options that differ from their defaults, by their
        0.4 names) and the one start option the run's start reads (`seed_points` as resolved), each written once
        its default changed."""
        keys = {"after-add": self.describe_restarts(), "reset-after-add": str(bool(self.every_round))}
        if seed_points == "active":  # a checkpoint without it (0.3's) never restarted
            keys["after-add.restart-active-starts"] = str(bool(self.active_starts))
        elif not random_start:  # the capture's points: before the default, such a start never restarted
            keys["after-add.restart-seeded-starts"] = str(bool(self.seeded_starts))
        return keys

    def describe_restarts(self) -> str:
        """The view-count options that differ from their defaults (seeded-starts aside: it has its own key), as
        0.4's after-add flags named them ("restart-at-views 8 16, restart-random-starts False"), or "off"."""
        on = []
        if self.at_views:
            on.append(f"restart-at-views {' '.join(map(str, self.at_views))}")
        if not self.random_starts:
            on.append("restart-random-starts False")
        if not self.active_starts:
            on.append("restart-active-starts False")
        return ", ".join(on) if on else "off"


@dataclass(frozen=True)
class RestartOutcome:
    """The splat back at its step-0 Gaussians after a round (every-round, or a restart at a view count)."""

    num_gaussians_before: int
    num_gaussians_after: int
    """After the reset and the points the restart starts from."""
    points: Optional[PointsOutcome] = None
    """`seed-points active`: the points all active views triangulated for the restart (it replaces the round's own
    seed points)."""

    @property
    def triangulated(self) -> bool:
        return self.points is not None

    def recorded_in(self, record: Any) -> Any:
        """`record` (a `RoundRecord`) with this restart."""
        record = dataclasses.replace(record, reset=True, num_gaussians_before_reset=self.num_gaussians_before,
                                     num_gaussians_after_reset=self.num_gaussians_after)
        return record if self.points is None else self.points.recorded_in(record)


class Restarts(Strategy):
    """Starts the splat over after the rounds `RestartsConfig` names."""

    def __init__(self, config: RestartsConfig) -> None:
        self.config = config
        self.counts: Tuple[int, ...] = ()
        """The view counts this run restarts at (set by `plan`)."""

    @property
    def resets_every_round(self) -> bool:
        return bool(self.config.every_round)

    def at_start(self, model: Any, start: RunStart) -> Dict[str, str]:
        return self.config.signature(start.seed_points, bool(getattr(model, "random_start", True)))

    def plan(self, model: Any, plan: RoundsPlan) -> None:
        """Fix the view counts of the restarts to come, say them at start where a start's default decides them, and
        keep the step-0 Gaussians in checkpoints while any may come."""
        cfg = self.config
        random_start = bool(getattr(model, "random_start", False))
        active_mode = plan.seed_points == "active"
        self.counts = cfg.restart_counts(plan.initial_views, random_start, active_mode and not random_start,
                                         plan.final_views)
        if cfg.every_round or self.counts:
            model.keep_initial_for_resets()
        if cfg.at_views and cfg.every_round:
            CONSOLE.print(f"[yellow]{FLAG}at-views does nothing with {FLAG}every-round: the splat restarts after every "
                          "round", soft_wrap=True)
        elif cfg.at_views and not self.counts:
            CONSOLE.print(f"[yellow]{FLAG}at-views {' '.join(map(str, cfg.at_views))} does nothing: this run goes from "
                          f"{plan.initial_views} to {plan.final_views} views", soft_wrap=True)
        if self.counts and not cfg.at_views:  # HP-GS's 20 + 7: none
            if random_start:
                what, source, flag = "random start", "", "random-starts"
            elif active_mode:
                what, source, flag = "active seed points", " from what the active views triangulate then", "active-starts"
            else:
                what, source, flag = "seed points", " from the capture's points", "seeded-starts"
            CONSOLE.print(f"{what}: the splat restarts at {' and '.join(map(str, self.counts))} views{source} "
                          f"({FLAG}{flag} False: never)", soft_wrap=True)

    def after_round(self, model: Any, added: RoundAdded) -> Optional[RestartOutcome]:
        if self.config.every_round:
            before = self.reset(model, added, squeeze=False)
            return RestartOutcome(before, int(model.num_points))
        if not any(added.views_before < n <= added.views_after for n in self.counts):
            return None
        before = self.reset(model, added, squeeze=True)
        points = self.reseed(model, added) if added.triangulate is not None else None
        return RestartOutcome(before, int(model.num_points), points)

    def reset(self, model: Any, added: RoundAdded, squeeze: bool) -> int:
        """The model back to its step-0 state and every schedule restarted at the round's step; `squeeze`: the
        schedules run in the steps left. Returns the Gaussians before."""
        if added.optimizers is None or not hasattr(model, "reset_to_initial"):
            raise RestartError("a restart needs the hpgs model and the trainer's optimizers")
        step, before = int(added.step), int(model.num_points)
        model.reset_to_initial(step, added.optimizers.optimizers)
        if not squeeze:
            restart_schedules(added.optimizers)
            what = f"reset after add: {before} -> {model.num_points} Gaussians, schedules restart at step {step}"
        else:
            left = max(int(added.end) - step, 1)
            model.set_clock_scale(left / max(int(added.end), 1))
            restart_schedules(added.optimizers, span=left)
            what = (f"restart at {added.views_after} views: {before} -> {model.num_points} Gaussians, "
                    f"every schedule reruns in the {left} steps left")
        CONSOLE.print(what)
        writer.put_scalar("selection/num_gaussians_before_reset", before, step)
        return before

    def reseed(self, model: Any, added: RoundAdded) -> PointsOutcome:
        """`seed-points active`: the splat starts over from the points the active views triangulate now (not from
        the initial views' few, or random, points); with too few, from its step-0 Gaussians."""
        start = time.perf_counter()
        xyz, rgb, info = added.triangulate()
        count = model.replace_gaussians(xyz, rgb, added.optimizers) if info.ok else 0
        if count:
            CONSOLE.print(f"restart: the splat starts from {count} points triangulated from {added.views_after} views")
        else:
            CONSOLE.print(f"[yellow]restart: {info.message or 'no points triangulated'}; the splat starts from its "
                          "step-0 Gaussians", soft_wrap=True)
        return PointsOutcome(restart=int(count), seconds=float(time.perf_counter() - start))
