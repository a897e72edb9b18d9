"""When the splat starts over as rounds add views: `--pipeline.selection.after-add.*`.

splatfacto keys everything to step 0: the means' learning rate decays to its floor, densification stops at
`stop-split-at` and opacity resets come every `reset-alpha-every` refines. A view added late meets a splat that can
no longer move, grow or drop what the first few views built from too little evidence. A restart at set view counts
drops that and trains the views present then together, as from step 0, in the steps left.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Dict, Iterable, Optional, Tuple

from hpgs_ns.errors import OptionError


class AfterAddError(OptionError):
    """An after-add option value that makes no sense (not a ValueError: tyro would draw its own box)."""


@dataclass
class AfterAddConfig:
    """When the splat starts over as rounds add views."""

    restart_at_views: Tuple[int, ...] = ()
    """Start the splat over when a round brings the number of training views to each of these counts (e.g. 8 16):
    the Gaussians go back to their step-0 state, and the learning-rate schedules and splatfacto's step-keyed
    schedule (densification, opacity resets, SH degree, resolution) run again, squeezed into the steps left. What
    the first few views built from too little evidence (floaters in front of views that came later) is dropped;
    the views then train together, as they would from step 0. Empty: see restart-random-starts."""
    restart_random_starts: bool = True
    """When restart-at-views is empty, a splat that started from random points (seed-points colmap without a point
    cloud, random-init or seed-points random) restarts at twice and four times the initial view count (FisherRF's 4 views: at 8 and 16;
    HP-GS's 20 + 7: never). Random starts lock in what the first views built; seeded ones barely do
    (docs/active-training.md). False: never restart unless restart-at-views says so."""

    restart_active_starts: bool = True
    """When restart-at-views is empty, a splat seeded by `seed-points active` restarts too, at twice and four times
    the initial view count, from the points all active views triangulate then: what a few initial views triangulate
    is thin (a few initial views triangulate hundreds of points, the final views thousands), and what the splat grew
    from it is locked in as a random start's is (docs/active-training.md). False: an active start that found enough
    points never restarts."""

    restart_seeded_starts: bool = True
    """When restart-at-views is empty, a splat seeded by the capture's points (seed-points colmap or colmap-initial,
    or auto where the capture has a point cloud) restarts too, at twice and four times the initial view count, from
    those points: the views present then train together as from step 0, so the order the views came in costs
    little (docs/active-training.md). False: such a splat never restarts unless restart-at-views says so (the
    behaviour before this default)."""

    def __post_init__(self) -> None:
        self.restart_at_views = tuple(int(n) for n in self.restart_at_views)
        if any(n < 1 for n in self.restart_at_views):
            raise AfterAddError(f"--pipeline.selection.after-add.restart-at-views {' '.join(map(str, self.restart_at_views))}: "
                                "view counts must be >= 1")

    def restart_counts(self, initial_views: int, random_start: bool, active_start: bool = False,
                       final_views: Optional[int] = None) -> Tuple[int, ...]:
        """The view counts at which the splat restarts, for a run of `initial_views` initial views that started from
        random points (`random_start`), from the initial views' triangulation (`active_start`) or, neither, from the
        capture's points, and that ends with `final_views` (counts beyond it never come)."""
        counts: Tuple[int, ...] = ()
        seeded_start = not random_start and not active_start
        if self.restart_at_views:
            counts = self.restart_at_views
        elif ((self.restart_random_starts and random_start) or (self.restart_active_starts and active_start)
              or (self.restart_seeded_starts and seeded_start)):
            counts = (2 * initial_views, 4 * initial_views)  # FisherRF's 4 views: 8 and 16
        if final_views is not None:
            counts = tuple(n for n in counts if initial_views < n <= final_views)
        return tuple(sorted(set(counts)))

    def start_keys(self, seed_points: str, random_start: bool) -> Dict[str, str]:
        """The resume signature's keys for the restart option the run's start reads (`seed_points` as resolved):
        each was written once its default changed, so a checkpoint without it resumes as it trained
        (`hpgs_ns.compat.seeded_restarts_key`)."""
        if seed_points == "active":  # a checkpoint without it (0.3's) never restarted
            return {"after-add.restart-active-starts": str(bool(self.restart_active_starts))}
        if not random_start:  # the capture's points: before the default, such a start never restarted
            return {"after-add.restart-seeded-starts": str(bool(self.restart_seeded_starts))}
        return {}

    def describe(self, skip: Iterable[str] = ()) -> str:
        """The options that differ from the defaults, as flags (for the log, the start-up line and the resume check),
        leaving out the fields named in `skip`."""
        def words(value) -> str:
            return " ".join(map(str, value)) if isinstance(value, tuple) else str(value)

        changed = [f for f in fields(self) if getattr(self, f.name) != f.default and f.name not in skip]
        on = [f"{f.name.replace('_', '-')} {words(getattr(self, f.name))}" for f in changed]
        return ", ".join(on) if on else "off"


def restarts_at(counts: Tuple[int, ...], views_before: int, views_after: int) -> bool:
    """Whether a round that took the training views from `views_before` to `views_after` crosses a restart count."""
    return any(views_before < n <= views_after for n in counts)
