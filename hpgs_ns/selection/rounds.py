"""Selection rounds: when they happen, what the selector sees, what follows an add, and the round log.

Every `select_every` steps (never at step 0), or at the `select_at` steps, before that step's training iteration,
the configured selector scores the withheld views and the chosen ones join the active set, until `max_rounds`
rounds have run or the pool is empty. Rounds run from a BEFORE_TRAIN_ITERATION callback because splatfacto's
densification reads state left by the last training render (`model.info`), so nothing may be rendered between
backward and the strategy step.

The datamanager owns which views are active (and saves them, with the round records, in every checkpoint); the
model owns rendering and its trainer strategies (a restart after a round is one, `hpgs_ns.strategies.restarts`);
the selector owns scoring. This class asks each for its part. Its options are
`hpgs_ns.selection.config.SelectionConfig` (`--pipeline.selection.*`).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from hpgs_ns.errors import UserError
from hpgs_ns.scenes.triangulate import away_from_splat
from hpgs_ns.selection.candidate_log import CandidateLog
from hpgs_ns.selection.early_stop import GainModel
from hpgs_ns.selection.log import FILE_NAME, SelectionLog
from hpgs_ns.selection.records import RoundFollowUp, RoundRecord, StopRecord
from hpgs_ns.selection.schedule import Every, run_steps
from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, Selector, check_selection
from hpgs_ns.strategies.base import PointsOutcome, RoundAdded, RoundsPlan


class RoundError(UserError, RuntimeError):
    """A selection round cannot run as configured."""


class RoundProgress:
    """A rich progress bar of the views a selector renders, shown from the first one it reports (a selector that
    renders nothing shows none). Its total is the round's active views and candidates, one pass over each."""

    def __init__(self, description: str, total: int) -> None:
        self.description, self.total = description, max(int(total), 1)
        self.bar: Optional[Progress] = None
        self.task = None

    def advance(self, views: int) -> None:
        if self.bar is None:
            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed} views"),
                                TimeElapsedColumn(), console=CONSOLE, transient=True)
            self.bar.start()
            self.task = self.bar.add_task(self.description, total=self.total)
        self.bar.advance(self.task, int(views))

    def __enter__(self) -> RoundProgress:
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.stop()


class SelectionRounds:
    """Runs the selection rounds of one training run (see the module docstring)."""

    def __init__(self, config, datamanager, model, selector: Optional[Selector] = None) -> None:
        self.config = config
        """`SelectionConfig`."""
        self.datamanager = datamanager
        self.model = model
        self.seed = int(datamanager.config.seed)
        self.schedule = Every(config.select_every, config.select_at)
        # A run without rounds (a final-set, `max-rounds 0`) never builds its selector: no preference model to load.
        self._selector = selector if selector is not None or config.max_rounds == 0 else config.build_selector()
        self.run_dir: Optional[Path] = None
        # Called with each round's finished record (what followed the add included) once it is logged: the viewer
        # redraws the roles.
        self.listeners: List[Callable[[RoundRecord], None]] = []
        # Scores the candidates as the selector saw them, so it runs before anything follows the add.
        self.candidate_log: Optional[CandidateLog] = CandidateLog(self) if config.log_candidate_scores else None
        self.gain_model = GainModel.load(config.gain_model) if config.stop_when_gain_below is not None else None
        self.stopped: Optional[StopRecord] = None
        """Why selection stopped early, once it has."""
        self.psnr_without_round: Dict[int, float] = {}
        """eval-each-round: test PSNR at scheduled steps where no round ran (this process's only)."""

    @property
    def selector(self) -> Selector:
        if self._selector is None:
            self._selector = self.config.build_selector()
        return self._selector

    @selector.setter
    def selector(self, value: Selector) -> None:
        self._selector = value

    # ---- when ------------------------------------------------------------------------------------------------

    def is_scheduled(self, step: int) -> bool:
        """Whether `step` is on the round schedule (select-at, or a multiple of select-every), rounds left or not."""
        return step in self.schedule

    def is_round_step(self, step: int) -> bool:
        """True when a selection round is due at `step`."""
        if step not in self.schedule:
            return False
        history = self.datamanager.history
        done = {h.step for h in history}
        due = step not in done and len(history) < self.config.max_rounds and bool(self.datamanager.candidates)
        return due and self.stopped is None and not self._stop_before(step)

    def predicted_gain(self) -> Optional[float]:
        """The test-PSNR gain (dB) the gain model predicts for the next round, if stop-when-gain-below is on."""
        if self.gain_model is None:
            return None
        return self.gain_model.predict(self.config.selector, len(self.datamanager.active))

    def _stop_before(self, step: int) -> bool:
        """stop-when-gain-below: True (and the stop recorded) when the next round is predicted to gain too little."""
        gain = self.predicted_gain()
        if gain is None or gain >= self.config.stop_when_gain_below:
            return False
        views = len(self.datamanager.active)
        self.stopped = StopRecord(int(step), views, float(gain), float(self.config.stop_when_gain_below))
        CONSOLE.print(f"[bold]selection stops at step {step}[/bold]: the next view is predicted to gain {gain:.2f} dB "
                      f"(< stop-when-gain-below {self.config.stop_when_gain_below:g}); {views} views")
        self.write_log()
        return True

    def plan(self, first_step: int, end_step: int) -> Tuple[int, str]:
        """How many rounds a run of steps [first_step, end_step) will run, and why not all `max_rounds` when
        fewer ("" when all do)."""
        cfg, dm = self.config, self.datamanager
        if cfg.max_rounds <= 0:
            return 0, f"max-rounds {cfg.max_rounds}"
        left = cfg.max_rounds - len(dm.history)
        if left <= 0:
            return 0, f"all {cfg.max_rounds} rounds already ran"
        steps = self.schedule.between(first_step, end_step)
        if cfg.select_at:
            too_late = f"only {len(steps)} select-at steps come before the last step ({end_step - 1})"
        elif cfg.select_every > 0:
            too_late = f"select-every {cfg.select_every} leaves {len(steps)} round steps before the last step ({end_step - 1})"
        else:
            too_late = f"select-every {cfg.select_every} and no select-at"
        done = {h.step for h in dm.history}
        steps = [s for s in steps if s not in done]
        candidates = len(dm.candidates)
        pool = math.ceil(candidates / max(cfg.views_per_round, 1))
        count = min(len(steps), left, pool)
        if count == left:
            return count, ""
        if pool < min(len(steps), left):
            if candidates == 0:
                return 0, "no withheld views to add (the initial views are the whole training split)"
            return count, f"only {candidates} withheld views to add ({cfg.views_per_round} per round)"
        return count, too_late

    def check_shortlist(self, rounds: int) -> None:
        """At start: a shortlist that would keep fewer views than a round adds, in the last of `rounds` rounds (the
        smallest pool), is one line now rather than a failure hours in."""
        from hpgs_ns.selectors.shortlist import shortlist_count

        cfg = self.config
        if not cfg.uses_shortlist():
            return
        pool = len(self.datamanager.candidates) - (rounds - 1) * cfg.views_per_round
        if pool <= 0:
            return
        kept = shortlist_count(cfg.shortlist_size, pool)
        if kept < min(cfg.views_per_round, pool):
            raise RoundError(
                f"--pipeline.selection.shortlist-size {cfg.shortlist_size:g} keeps {kept} of the last round's {pool} "
                f"candidates, fewer than the {cfg.views_per_round} views a round adds; raise it to at least "
                f"{min(cfg.views_per_round / pool, 1):.2f} or lower --pipeline.selection.views-per-round")

    def callbacks(self, attrs: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """The BEFORE_TRAIN_ITERATION callback that runs rounds (and what follows each), and one that writes the final
        log. Says at start what the run will do (`announce`) and tells the model's strategies the rounds' plan."""
        trainer = attrs.trainer
        if trainer is not None and getattr(trainer, "base_dir", None) is not None:
            self.run_dir = Path(trainer.base_dir)
        first, end = run_steps(trainer) if trainer is not None else (0, 0)
        count = self.announce(first, end) if trainer is not None else None
        if hasattr(self.model, "plan_rounds"):
            self.model.plan_rounds(self.rounds_plan(count))
        active_mode = getattr(self.datamanager, "seed_points_mode", None) == "active"
        self.tell_strategies()  # the active views as the run starts (a resumed run's: its checkpoint's)

        def before_iteration(step: int) -> None:
            if step == first:
                self.write_log()
            if self.is_round_step(step):
                before = len(self.datamanager.active)
                self.run_round(step)
                follow_up = self.after_round(step, attrs.optimizers, before, end, active_mode)
                self.tell_strategies()
                # The round is recorded once, with what followed the add, and logged once.
                self.datamanager.history[-1] = follow_up.recorded_in(self.datamanager.history[-1])
                self.write_log()
                for listener in self.listeners:  # the finished record
                    listener(self.datamanager.history[-1])
            elif self.config.eval_each_round and self.is_scheduled(step):
                # No round here (none left, or a reference run): the test PSNR at the step still says what the
                # views so far are worth against a run that added others (early_stop's calibration).
                self.psnr_without_round[int(step)] = self.test_psnr()

        callbacks = [TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before_iteration)]
        if trainer is not None:
            callbacks.append(
                TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], lambda step: self.write_log(), iters=(end - 1,))
            )
        return callbacks

    def announce(self, first: int, end: int) -> int:
        """At start, for a run of steps [first, end): say when fewer rounds than `max-rounds` will run and why, what
        early stop predicts, and which selection options do nothing (`SelectionConfig.shortlist_notes`,
        `idle_selector_options`); check the shortlist against the last round. Returns the rounds still to run."""
        count, why = self.plan(first, end)
        gain = self.predicted_gain()
        if gain is not None:
            CONSOLE.print(f"stop-when-gain-below {self.config.stop_when_gain_below:g} dB: the first round is predicted "
                          f"to gain {gain:.2f} dB; selection stops at the first round predicted below it")
        if why:
            ran = len(self.datamanager.history)  # rounds a resumed run ran before its checkpoint
            if count == 0:
                what = f"no more selection rounds will run ({ran} ran before the checkpoint)" if ran else \
                    "no selection rounds will run"
            else:
                what = f"only {ran + count} of {self.config.max_rounds} selection rounds will run"
                what += f" ({ran} before the checkpoint, {count} from step {first})" if ran else ""
            CONSOLE.print(f"[yellow]{what}: {why}", soft_wrap=True)
        for note in self.config.shortlist_notes() + self.config.idle_selector_notes():
            CONSOLE.print(f"[yellow]{note}", soft_wrap=True)
        if count:
            self.check_shortlist(count)
        return count

    def rounds_plan(self, count: Optional[int]) -> RoundsPlan:
        """The rounds as strategies see them at start; `count`: the rounds still to run (None: as configured)."""
        dm = self.datamanager
        if count is None:
            final = min(len(dm.initial_views) + self.config.max_rounds * self.config.views_per_round,
                        len(dm.active) + len(dm.candidates))
        else:  # what is active now and what the rounds still to run add
            final = len(dm.active) + min(count * self.config.views_per_round, len(dm.candidates))
        return RoundsPlan(initial_views=len(dm.initial_views), final_views=int(final),
                          seed_points=str(getattr(dm, "seed_points_mode", None) or "colmap"))

    def tell_strategies(self) -> None:
        """Give the model's trainer strategies (`hpgs_ns.strategies`), if it runs any, the active views and the
        points they see now (after a round: once its follow-up, e.g. `seed-points active`'s triangulation, ran)."""
        if getattr(self.model, "trainer_strategies", None) and hasattr(self.datamanager, "active_views"):
            self.model.after_views_added(self.datamanager.active_views())

    def after_round(self, step: int, optimizers, before: int, end: int, active_mode: bool) -> RoundFollowUp:
        """What follows a round's add: the model's strategies (a restart, and the points it starts from), then
        `seed-points active`'s new points unless a restart triangulated every active view already."""
        dm = self.datamanager
        active_seeds = active_mode and optimizers is not None
        added = RoundAdded(step=int(step), end=int(end), views_before=int(before), views_after=len(dm.active),
                           optimizers=optimizers, triangulate=dm.triangulate_active if active_seeds else None)
        outcomes = tuple(self.model.after_round(added)) if hasattr(self.model, "after_round") else ()
        points = None
        if active_seeds and not any(getattr(o, "triangulated", False) for o in outcomes):
            points = self.add_seed_points(step, optimizers)
        return RoundFollowUp(outcomes, points)

    # ---- one round -------------------------------------------------------------------------------------------

    def context(self, step: int) -> SelectionContext:
        """The typed context a selector sees for a round at `step`."""
        dm, model = self.datamanager, self.model
        candidates = dm.candidates
        cameras = dm.train_dataset.cameras
        short = self.config.render_short_side
        return SelectionContext(
            step=step,
            round_index=len(dm.history),
            active=list(dm.active),
            candidates=candidates,
            num_to_pick=min(self.config.views_per_round, len(candidates)),
            cameras=cameras,
            image_names=dm.image_names,
            model=model,
            render=lambda idx, short_side=short: model.render_views(
                cameras[torch.tensor([int(i) for i in idx], dtype=torch.long)], short_side
            ),
            # Derived from (seed, round) so a resumed run makes the same choices as an uninterrupted one.
            generator=torch.Generator().manual_seed(self.seed * 1_000_003 + len(dm.history)),
            device=torch.device(model.device),
        )

    def run_round(self, step: int) -> Selection:
        """Ask the selector for views, make them active, and record the round (`after_round` follows; the caller
        logs the finished round)."""
        dm = self.datamanager
        test_psnr = self.test_psnr() if self.config.eval_each_round else None
        context = self.context(step)
        if not context.candidates:
            raise SelectionError("no withheld views left to select from")
        start = time.perf_counter()
        with RoundProgress(f"selection round {len(dm.history) + 1} ({self.config.selector})",
                           len(context.active) + len(context.candidates)) as progress:
            context.progress = progress.advance
            selection = check_selection(self.selector.select(context), context)
        seconds = time.perf_counter() - start
        names = dm.image_names
        dm.activate(selection.indices)
        record = RoundRecord(
            round=len(dm.history) + 1,
            step=int(step),
            selector=self.config.selector,
            chosen=[names[i] for i in selection.indices],
            chosen_indices=[int(i) for i in selection.indices],
            seconds=float(seconds),
            num_active=len(dm.active),
            test_psnr_before=test_psnr,
            scores={names[i]: float(s) for i, s in selection.scores.items()},
            work={k: float(v) for k, v in selection.work.items()},
        )
        dm.history.append(record)
        CONSOLE.print(
            f"[bold green]View selection round {record.round} at step {step}[/bold green]: "
            f"+ {', '.join(record.chosen)} ({self.config.selector}, {seconds:.2f} s, {len(dm.active)} active)"
        )
        writer.put_scalar("selection/seconds", seconds, step)
        writer.put_scalar("selection/num_active", len(dm.active), step)
        self._log_chosen_render(selection.indices[0], step)
        self._log_scores_plot(selection, step)
        if self.candidate_log is not None:
            self.candidate_log.on_round(record)
        return selection

    def add_seed_points(self, step: int, optimizers) -> PointsOutcome:
        """`seed-points active`: triangulate the active views again (the round's new views with the earlier ones,
        whose features and matches the datamanager's workspace keeps) and add the points away from the splat as new
        Gaussians. Returns what it did."""
        dm, model = self.datamanager, self.model
        start = time.perf_counter()
        xyz, rgb, info = dm.triangulate_active()
        added = 0
        if info.failed:
            CONSOLE.print(f"[yellow]seed points after round {len(dm.history)}: {info.message}; no Gaussians added", soft_wrap=True)
        elif xyz.shape[0]:
            away = away_from_splat(model.means, xyz)
            added = model.add_gaussians(xyz[away], rgb[away], optimizers)
        seconds = time.perf_counter() - start
        if not info.failed:  # a failure had its one line above
            CONSOLE.print(f"seed points after round {len(dm.history)}: {xyz.shape[0]} triangulated from {len(dm.active)} "
                          f"views, {added} away from the splat added ({model.num_points} Gaussians, {seconds:.1f} s)")
        writer.put_scalar("selection/seed_points_added", added, step)
        return PointsOutcome(added=int(added), seconds=float(seconds))

    @torch.no_grad()
    def test_psnr(self) -> float:
        """Mean PSNR over the test views with the current splat (eval mode)."""
        from hpgs_ns.metrics import photo_rgb, psnr

        model = self.model
        with model.eval_mode():
            values = []
            for camera, batch in self.datamanager.fixed_indices_eval_dataloader:
                rgb = model.get_outputs_for_camera(camera)["rgb"].clamp(0, 1)
                values.append(psnr(rgb.cpu(), photo_rgb(batch["image"]).cpu()))
            return float(np.mean(values)) if values else float("nan")

    # ---- the round log ---------------------------------------------------------------------------------------

    def write_log(self) -> Optional[Path]:
        """Write `selected_views.json` in the run directory (temp file, then rename)."""
        if self.run_dir is None:
            return None
        return self.log().write(self.run_dir / FILE_NAME)

    def log(self) -> SelectionLog:
        """The round log as it stands: the datamanager's views and records, and what this loop measured."""
        dm = self.datamanager
        names = dm.image_names
        return SelectionLog(
            selector=self.config.selector,
            seed=self.seed,
            reset_after_add=any(getattr(s, "resets_every_round", False) for s in getattr(self.model, "trainer_strategies", [])),
            seed_points=getattr(dm, "seed_points_mode", None),  # as resolved: `auto` is colmap or active
            random_start=bool(getattr(self.model, "random_start", False)),  # that mode found no points
            initial=[names[i] for i in dm.initial_views],
            rounds=list(dm.history),
            active=[names[i] for i in dm.active],
            withheld=[names[i] for i in dm.candidates],
            test=dm.test_view_names,
            peak_gpu_memory_mb=torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None,
            stopped=self.stopped,
            test_psnr_at_round_steps=self.test_psnr_at_round_steps(),
        )

    def test_psnr_at_round_steps(self) -> Dict[int, float]:
        """eval-each-round: the test PSNR at every scheduled step, before its round if one ran ({step: dB})."""
        values = {h.step: h.test_psnr_before for h in self.datamanager.history if h.test_psnr_before is not None}
        values.update(self.psnr_without_round)
        return {int(k): float(values[k]) for k in sorted(values)}

    def _log_chosen_render(self, index: int, step: int) -> None:
        try:
            cameras = self.datamanager.train_dataset.cameras[torch.tensor([int(index)], dtype=torch.long)]
            image = self.model.render_views(cameras, self.config.render_short_side)[0]
            writer.put_image("selection/chosen_view", image.cpu(), step)
        except Exception as err:  # logging must never stop training
            CONSOLE.print(f"[yellow]could not log the chosen view's render: {err}")

    def _log_scores_plot(self, selection: Selection, step: int) -> None:
        """Candidates' scores as an image in the writer (nerfstudio's writer has no histogram)."""
        if len(set(selection.scores.values())) < 2:
            return
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            items = sorted(selection.scores.items(), key=lambda kv: -kv[1])
            fig, ax = plt.subplots(figsize=(6, 2.4), dpi=80)
            ax.bar(range(len(items)), [v for _, v in items],
                   color=["C3" if i in selection.indices else "C0" for i, _ in items], width=1.0)
            ax.set(xlabel="candidates (sorted)", ylabel="score", title=f"{self.config.selector} scores, step {step}")
            fig.tight_layout()
            fig.canvas.draw()
            image = torch.from_numpy(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()).float() / 255
            plt.close(fig)
            writer.put_image("selection/scores", image, step)
        except Exception as err:  # logging must never stop training
            CONSOLE.print(f"[yellow]could not plot the selection scores: {err}")
