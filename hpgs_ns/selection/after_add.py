"""What training does when a round adds views: `--pipeline.selection.after-add.*`.

splatfacto keys everything to step 0: the means' learning rate decays to its floor, densification stops at
`stop-split-at` and opacity resets come every `reset-alpha-every` refines. A view added late meets a splat that can
no longer move, grow or drop what the first views built (floaters in front of the new view stay). Measured on the
GPU: fox (random start) loses 8 dB against the same 20 views trained from step 0 (shared/design/schedule-pilot.md).
Each mechanism below gives the views that arrive late some of what the early ones had; all off is 0.3's schedule.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Dict, Iterable, Literal, Optional, Tuple

from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns.errors import OptionError
from hpgs_ns.schedules import restart_schedules


class AfterAddError(OptionError):
    """An after-add option value that makes no sense (not a ValueError: tyro would draw its own box)."""


@dataclass
class AfterAddConfig:
    """How training reacts to views added by a round."""

    refine_steps: int = 0
    """Densify, split and cull for this many steps after each add, even past splatfacto's stop-split-at (and with
    its periodic opacity resets and its screen-size split and cull inside that window): the new view can grow
    Gaussians where it sees detail and prune the ones it shows to be floaters (one just in front of it fills its
    screen). 0: refinement ends at stop-split-at whatever arrives after it."""
    reset_opacity: bool = False
    """Reset opacities at each add, as splatfacto does every reset-alpha-every refines: Gaussians the views do not
    need fade out and are culled, including floaters that only the first views tolerated."""
    lr_rewind: int = 0
    """Rewind the learning-rate schedules (the means' decay, the camera optimizer's) by this many steps at each add,
    so the Gaussians can still move to fit the new view. 0: the schedules run from step 0 untouched."""
    lr_restart: bool = False
    """At each add, every learning-rate schedule starts over (from its initial rate; schedules with a warm-up, such as
    the camera optimizer's, warm up again) and decays to its final rate by the end of the run (a warm restart
    squeezed into the steps left), the Gaussians kept: the means can still move to fit a late view, and the run
    still ends at the floor rate (repeated lr-rewinds can leave it high). Not with lr-rewind."""
    restart_at_views: Tuple[int, ...] = ()
    """Start the splat over when a round brings the number of training views to each of these counts (e.g. 8 16):
    the Gaussians go back to their step-0 state, and the learning-rate schedules and splatfacto's step-keyed
    schedule (densification, opacity resets, SH degree, resolution) run again, squeezed into the steps left. What
    the first few views built from too little evidence (floaters in front of views that came later) is dropped;
    the views then train together, as they would from step 0. Empty: see restart-random-starts. A restart round
    runs no other after-add option."""
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

    restart_at_last_add: bool = False
    """Also start the splat over at the round that brings the training views to the run's final count (initial
    views + max-rounds x views-per-round, or every view if fewer remain): the final views then train together, as
    from step 0, in the steps left (FisherRF's protocol: at 20 views, step 18400, 1600 steps; HP-GS's: at 27, step
    14000, 1000 steps). Off: on the tuning scenes it did not gain in the `active` start (docs/active-training.md).
    Not with reset-after-add; a run whose selection stops early (stop-when-gain-below) never reaches that count and
    does not restart."""
    restart_from: Literal["start", "splat"] = "start"
    """What a restart starts from. `start`: the run's step-0 points (its seed points or random points; with
    `seed-points active`, what the active views triangulate then; with `random-points views`, points drawn again
    along the active views' rays). `splat`: the splat's own Gaussians as points (centres and base colours of those
    at least cull-alpha-thresh opaque) with fresh sizes, rotations and opacities: where the views so far put
    surfaces, without the shapes and opacities the first views fixed (with `seed-points active`, the round's
    triangulated points away from them join, as after any round). None opaque: that restart starts as `start` does.
    Meant for captures without seed points, whose restarts otherwise begin from random points again; off because
    on the tuning scenes it scattered the splat into fragments (docs/active-training.md). Not with
    reset-after-add (which always returns to the step-0 Gaussians)."""

    error_points: int = 0
    """After each add that is not a restart, for each view it added: render the splat from the view and add this
    many Gaussians on the rays of the pixels the render gets most wrong (drawn in proportion to their error above
    the view's median), in the photo's colours, at the render's depth where it is opaque and at a drawn distance
    where it is not (`hpgs_ns.scenes.error_points`). Content a late view shows first then starts from the view's own
    pixels instead of the few points its triangulation adds, or none. 0: off. Does nothing with reset-after-add."""

    def __post_init__(self) -> None:
        self.restart_at_views = tuple(int(n) for n in self.restart_at_views)
        if any(n < 1 for n in self.restart_at_views):
            raise AfterAddError(f"--pipeline.selection.after-add.restart-at-views {' '.join(map(str, self.restart_at_views))}: "
                                "view counts must be >= 1")
        for name, unit in (("refine_steps", "steps"), ("lr_rewind", "steps"), ("error_points", "points per view")):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                raise AfterAddError(f"--pipeline.selection.after-add.{name.replace('_', '-')} {value} must be a whole "
                                    f"number of {unit} >= 0 (0 turns it off)")

        if self.lr_restart and self.lr_rewind:
            raise AfterAddError("--pipeline.selection.after-add.lr-restart and lr-rewind both move the learning rates "
                                "at each add: pass one of them")

    @property
    def enabled(self) -> bool:
        """Whether an option that runs at every add is on (restarts run at their own rounds)."""
        return bool(self.refine_steps or self.reset_opacity or self.lr_rewind or self.lr_restart)

    def restart_counts(self, initial_views: int, random_start: bool, active_start: bool = False,
                       final_views: Optional[int] = None) -> Tuple[int, ...]:
        """The view counts at which the splat restarts, for a run of `initial_views` initial views that started from
        random points (`random_start`), from the initial views' triangulation (`active_start`) or, neither, from the
        capture's points, and that ends with `final_views` (restart-at-last-add; counts beyond it never come)."""
        counts: Tuple[int, ...] = ()
        seeded_start = not random_start and not active_start
        if self.restart_at_views:
            counts = self.restart_at_views
        elif ((self.restart_random_starts and random_start) or (self.restart_active_starts and active_start)
              or (self.restart_seeded_starts and seeded_start)):
            counts = (2 * initial_views, 4 * initial_views)
        if self.restart_at_last_add and final_views is not None:
            counts = (*counts, int(final_views))
        if final_views is not None:
            counts = tuple(n for n in counts if initial_views < n <= final_views)
        return tuple(sorted(set(counts)))

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


def rewind_schedules(schedulers: Dict[str, object], steps: int, names: Iterable[str] = ()) -> Dict[str, int]:
    """Move each learning-rate scheduler (`names`, default all) `steps` back along its schedule (not before its
    start). nerfstudio steps its schedulers once per iteration without a step, so `last_epoch` is the position; it is
    in the scheduler's state_dict, so `--load-dir` restores the rewound position. Returns {name: new position}."""
    chosen = set(names) or set(schedulers)
    positions = {}
    for name, scheduler in schedulers.items():
        if name not in chosen:
            continue
        position = max(int(scheduler.last_epoch) - int(steps), 0)
        scheduler.last_epoch = position - 1
        scheduler.step()  # -> last_epoch = position; every group's lr = initial lr x schedule(position)
        positions[name] = position
    return positions


def apply_after_add(config: AfterAddConfig, model, optimizers, step: int, end: Optional[int] = None) -> Dict[str, float]:
    """Run the enabled mechanisms for an add at trainer step `step` of a run that ends at step `end` (lr-restart);
    returns what was done (for the round log)."""
    done: Dict[str, float] = {}
    if config.refine_steps:
        done["refine_until"] = float(model.extend_refinement(step + config.refine_steps))
    if config.reset_opacity:
        done["opacity_reset"] = float(model.reset_opacities(optimizers.optimizers))
    if config.lr_rewind:
        # Only the schedules that decay: the Gaussians' other groups run at constant rates.
        for name, position in rewind_schedules(optimizers.schedulers, config.lr_rewind).items():
            done[f"lr_position.{name}"] = float(position)
    if config.lr_restart and end is not None:
        left = max(int(end) - int(step), 1)
        restart_schedules(optimizers, span=left)
        done["lr_restart_span"] = float(left)
    if done:
        CONSOLE.print(f"after add (step {step}): " + ", ".join(f"{k} {v:g}" for k, v in done.items()))
    return done
