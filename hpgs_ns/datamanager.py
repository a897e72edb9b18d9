"""The active datamanager: trains on a growing subset of the training views, asking a selector for more.

Built on nerfstudio's `FullImageDatamanager`. The training split is divided into *active* views (sampled for
training) and withheld *candidates*; the test split is neither, ever. Every `select_every` steps (never at step
0), before the training iteration, the configured selector scores the candidates and the chosen ones join the
active set, until `max_rounds` rounds have run or the pool is empty.

Selection runs from a BEFORE_TRAIN_ITERATION callback because splatfacto's densification reads state left by
the last training render (`model.info`), so nothing may be rendered between backward and the strategy step.
The active set and round history are part of the datamanager's state (`get_extra_state`), so they are saved in
every checkpoint and restored by `--load-dir`, `ns-eval` and `ns-viewer`.

With `reset_after_add` (FisherRF's protocol) each round is followed by a reset: the model returns to its step-0
state and the learning-rate schedules restart (`HpgsSplatfactoModel.reset_to_initial`, `restart_schedules`).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple, Type

import numpy as np
import torch
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns.atomic_write import write_json_atomic
from hpgs_ns.dataparser import MipNerf360DataParserConfig
from hpgs_ns.errors import UserError
from hpgs_ns.selectors import (
    CondorcetSelectorConfig,
    FarthestSelectorConfig,
    FisherSelectorConfig,
    HpgsSelectorConfig,
    RandomSelectorConfig,
    Selection,
    SelectionContext,
    SelectionError,
    check_selection,
)
from hpgs_ns.selectors.base import eval_mode

SelectorName = Literal["random", "farthest", "fisher", "hpgs", "condorcet"]


class ActiveViewError(UserError, RuntimeError):
    """The active/withheld split cannot be set up or restored."""


@dataclass
class ActiveDatamanagerConfig(FullImageDatamanagerConfig):
    """Full-image datamanager that starts from a few views and adds the views a selector picks."""

    _target: Type = field(default_factory=lambda: ActiveDatamanager)
    dataparser: MipNerf360DataParserConfig = field(default_factory=MipNerf360DataParserConfig)  # type: ignore
    cache_images_type: Literal["uint8", "float32"] = "uint8"
    num_initial_views: int = 20
    """Training views active at step 0."""
    initial_views: Literal["even", "fps", "random"] = "even"
    """How the initial views are chosen: evenly spaced along the capture (file-name order); `fps`: the first
    view, then farthest camera centres (FisherRF's start); or uniformly at random (seeded)."""
    initial_view_names: Tuple[str, ...] = ()
    """Explicit initial views by image file name (overrides initial-views)."""
    select_every: int = 2000
    """A selection round runs at steps select_every, 2*select_every, ... (never at step 0)."""
    select_at: Tuple[int, ...] = ()
    """Explicit round steps (e.g. FisherRF's 400 900 1500 ...); when given, select-every is ignored."""
    views_per_round: int = 1
    """Views added per round (greedy batch selection when > 1)."""
    max_rounds: int = 7
    """Rounds before selection stops (HP-GS: 7 additions over 15000 steps)."""
    seed: int = 0
    """Seeds the initial views (random/fps) and the selectors' randomness."""
    selector: SelectorName = "hpgs"
    """Which selector picks the next views (default: the paper's human-preference selector)."""
    random: RandomSelectorConfig = field(default_factory=RandomSelectorConfig)
    """Options of the `random` selector."""
    farthest: FarthestSelectorConfig = field(default_factory=FarthestSelectorConfig)
    """Options of the `farthest` selector."""
    fisher: FisherSelectorConfig = field(default_factory=FisherSelectorConfig)
    """Options of the `fisher` selector (FisherRF)."""
    hpgs: HpgsSelectorConfig = field(default_factory=HpgsSelectorConfig)
    """Options of the `hpgs` selector (the paper's method)."""
    condorcet: CondorcetSelectorConfig = field(default_factory=CondorcetSelectorConfig)
    """Options of the `condorcet` selector (the paper's ablation)."""
    strict_init: bool = False
    """Keep only the COLMAP seed points whose track includes at least two initial views, so withheld and test
    views leak no geometry into the starting splat."""
    eval_each_round: bool = False
    """Measure test-view PSNR just before each round (recorded in selected_views.json; used by `hpgs bench`)."""
    snapshot_every: int = 0
    """If > 0, every this many steps (and at the last step) render every training-split view to
    `<run dir>/snapshots/step-NNNNNN/` (what `hpgs collect` labels). Test views are never rendered."""
    selection_short_side: Optional[int] = None
    """Default render size (short side, pixels) for selectors that render views; None = dataset resolution."""
    reset_after_add: bool = False
    """After each round, start training over from the new view set, as FisherRF (Jiang et al., ECCV 2024) does:
    the Gaussians go back to the step-0 ones, optimizer moments, densification state and camera optimizer are
    cleared, and learning rates and splatfacto's step-keyed schedule (densification, opacity reset, SH degree,
    resolution) restart at the round's step. The trainer's step keeps counting; the run ends at
    max-num-iterations."""


class ActiveDatamanager(FullImageDatamanager):
    """Samples training batches from the active views only and grows them by selection rounds."""

    config: ActiveDatamanagerConfig

    def __init__(self, config: ActiveDatamanagerConfig, device="cpu", test_mode="val", **kwargs):
        if torch.device(device).type == "cpu":
            # "gpu" caching means "on the datamanager's device"; "cpu" caching pins memory, which needs CUDA.
            config.cache_images = "gpu"
        super().__init__(config, device=device, test_mode=test_mode, **kwargs)
        self.image_names: List[str] = [Path(p).name for p in self.train_dataset.image_filenames]
        test_names = {Path(p).name for p in self.eval_dataset.image_filenames}
        overlap = test_names & set(self.image_names)
        assert not overlap, f"test views also in the training split: {sorted(overlap)[:5]}"
        self.generator = torch.Generator().manual_seed(self.config.seed)
        self.active: List[int] = self._initial_views()
        self.history: List[Dict[str, Any]] = []
        if self.config.strict_init:
            self._keep_points_seen_by_initial_views()
        # Only training selects; ns-eval / ns-viewer (test modes) must open a run without the selector's files.
        self.selector = self._setup_selector() if test_mode == "val" else None
        self.run_dir: Optional[Path] = None
        self._writer_ready = False
        self.train_unseen_cameras = self.sample_train_cameras()

    # ---- which views are active ----------------------------------------------------------------------------

    @property
    def candidates(self) -> List[int]:
        """Withheld training views, in index order."""
        active = set(self.active)
        return [i for i in range(len(self.train_dataset)) if i not in active]

    def _initial_views(self) -> List[int]:
        n, k = len(self.train_dataset), self.config.num_initial_views
        if self.config.initial_view_names:
            unknown = [v for v in self.config.initial_view_names if v not in self.image_names]
            if unknown:
                raise ActiveViewError(f"initial view {unknown[0]!r} is not a training image (test views cannot be used)")
            return sorted(self.image_names.index(v) for v in self.config.initial_view_names)
        if k < 1:
            raise ActiveViewError("--pipeline.datamanager.num-initial-views must be at least 1")
        if k >= n:
            CONSOLE.print(f"[yellow]num-initial-views={k} >= {n} training views: training on all of them")
            return list(range(n))
        if self.config.initial_views == "even":
            return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})
        if self.config.initial_views == "random":
            return sorted(torch.randperm(n, generator=self.generator)[:k].tolist())
        centres = self.train_dataset.cameras.camera_to_worlds[:, :3, 3]
        return sorted(farthest_point_order(centres, k, start=0))

    def _keep_points_seen_by_initial_views(self, min_views: int = 2) -> None:
        """Filter the dataparser's seed points in place (the pipeline hands them to the model after this)."""
        # nerfstudio's own COLMAP reader, as its dataparser used: the mask then lines up with its point order.
        from hpgs_ns.colmap_model import read_images, read_points3D

        meta = self.train_dataparser_outputs.metadata
        if "points3D_xyz" not in meta:
            return
        model_dir = Path(self.config.dataparser.data) / self.config.dataparser.colmap_path
        images, points = read_images(model_dir), read_points3D(model_dir)
        if images is None or points is None:
            raise ActiveViewError(f"strict-init needs {model_dir}/images and points3D (.bin or .txt); drop --pipeline.datamanager.strict-init")
        name_to_id = {im.name: im_id for im_id, im in images.items()}
        initial_ids = {name_to_id[self.image_names[i]] for i in self.active if self.image_names[i] in name_to_id}
        tracks = [set(p.image_ids.tolist()) for p in points.values()]
        if not any(tracks):
            raise ActiveViewError(
                f"{model_dir}/points3D has no point tracks (which images see each point), which strict-init needs; "
                "use the full COLMAP model or drop --pipeline.datamanager.strict-init"
            )
        keep = torch.tensor([len(initial_ids & track) >= min_views for track in tracks])
        if keep.numel() != meta["points3D_xyz"].shape[0]:
            raise ActiveViewError("seed points and COLMAP tracks disagree; re-run without --pipeline.datamanager.strict-init")
        if not keep.any():
            raise ActiveViewError(
                f"strict-init kept no seed point: none of {model_dir}/points3D is seen by {min_views} of the "
                f"{len(self.active)} initial views; use more initial views or drop --pipeline.datamanager.strict-init"
            )
        for key in [k for k, v in meta.items() if k.startswith("points3D_") and torch.is_tensor(v) and v.shape[:1] == keep.shape]:
            meta[key] = meta[key][keep]
        CONSOLE.print(f"strict init: kept {int(keep.sum())} of {keep.numel()} seed points seen by >= {min_views} initial views")

    def sample_train_cameras(self) -> List[int]:
        """A shuffled pass over the active views (nerfstudio calls this whenever a pass is used up)."""
        if not hasattr(self, "active"):  # called by the parent constructor before the split exists
            return [0]
        order = torch.randperm(len(self.active), generator=self.generator).tolist()
        return [self.active[i] for i in order]

    def next_train(self, step: int):
        camera, data = super().next_train(step)
        index = camera.metadata["cam_idx"]
        assert index in self.active, f"training view {index} is not active"
        return camera, data

    # ---- state saved in checkpoints ------------------------------------------------------------------------

    def get_extra_state(self) -> Dict[str, Any]:
        # Plain Python types only, so checkpoints load with torch.load(weights_only=True).
        return {"version": 1, "image_names": list(self.image_names), "active": list(self.active), "history": self.history}

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        if state.get("image_names") != self.image_names:
            raise ActiveViewError(
                "checkpoint's active views belong to a different scene or split; pass the --data it was trained on"
            )
        self.active = [int(i) for i in state["active"]]
        self.history = list(state["history"])
        self.train_unseen_cameras = self.sample_train_cameras()

    # ---- selection rounds ----------------------------------------------------------------------------------

    def _setup_selector(self):
        return getattr(self.config, self.config.selector).setup()

    def is_round_step(self, step: int) -> bool:
        """True when a selection round is due at `step`."""
        every = self.config.select_every
        if self.config.select_at:
            if step not in self.config.select_at:
                return False
        elif step <= 0 or every <= 0 or step % every != 0:
            return False
        done = {h["step"] for h in self.history}
        return step not in done and len(self.history) < self.config.max_rounds and bool(self.candidates)

    def get_training_callbacks(self, attrs: TrainingCallbackAttributes) -> List[TrainingCallback]:
        trainer = attrs.trainer
        if trainer is not None and getattr(trainer, "base_dir", None) is not None:
            self.run_dir = Path(trainer.base_dir)
        model = attrs.pipeline.model if attrs.pipeline is not None else None
        if self.config.reset_after_add and model is not None:
            model.keep_initial_in_checkpoint = True

        def before_iteration(step: int) -> None:
            if step == getattr(trainer, "_start_step", 0):
                self.write_log()
            if model is not None and self.is_round_step(step):
                self.run_round(step, model)
                if self.config.reset_after_add:
                    self.reset_model(step, model, attrs.optimizers)
            every = self.config.snapshot_every
            if model is not None and every > 0 and step > 0 and step % every == 0:
                self.write_snapshot(step, model)

        def after_training(step: int) -> None:
            every = self.config.snapshot_every
            if model is not None and every > 0 and (step + 1) % every == 0:
                self.write_snapshot(step + 1, model)
            self.write_log()

        callbacks = [TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before_iteration)]
        if trainer is not None:
            last = trainer.config.max_num_iterations - 1
            callbacks.append(
                TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after_training, iters=(last,))
            )
        return callbacks

    def write_snapshot(self, step: int, model) -> Optional[Path]:
        """Render every training-split view at `step` into `snapshots/step-NNNNNN/` (temp folder, then rename)."""
        if self.run_dir is None:
            return None
        from PIL import Image

        target = self.run_dir / "snapshots" / f"step-{step:06d}"
        if target.exists():
            return target
        tmp = Path(tempfile.mkdtemp(prefix=".snapshot-", dir=target.parent if target.parent.exists() else self._mk(target.parent)))
        for i in range(len(self.train_dataset)):
            image = self.render_views(model, [i])[0]
            array = (image.cpu().numpy() * 255 + 0.5).astype(np.uint8)
            Image.fromarray(array).save(tmp / f"{Path(self.image_names[i]).stem}.png")
        write_json_atomic(tmp / "views.json", {"step": step, "active": [self.image_names[i] for i in self.active]})
        tmp.rename(target)
        return target

    @staticmethod
    def _mk(path: Path) -> Path:
        path.mkdir(parents=True, exist_ok=True)
        return path

    @torch.no_grad()
    def render_views(self, model, indices: Sequence[int], short_side: Optional[int] = None, batch: int = 16) -> List[torch.Tensor]:
        """Render training-split views with the current splat, in eval mode; each [H, W, 3] in [0, 1].

        Views are rendered `batch` at a time in one rasterization call when the model can (`render_rgb_batch`)."""
        cameras = self.train_dataset.cameras[torch.tensor([int(i) for i in indices], dtype=torch.long)]
        if short_side is not None:
            scale = short_side / torch.minimum(cameras.width, cameras.height).float()
            cameras.rescale_output_resolution(scale)
        with eval_mode(model):
            if not hasattr(model, "render_rgb_batch"):
                return [model.get_outputs_for_camera(cameras[k : k + 1].to(model.device))["rgb"].clamp(0, 1) for k in range(len(indices))]
            images: List[torch.Tensor] = []
            for start in range(0, len(indices), batch):
                chunk = cameras[start : start + batch]
                if bool((chunk.width == chunk.width[0]).all()) and bool((chunk.height == chunk.height[0]).all()):
                    images += list(model.render_rgb_batch(chunk))
                else:
                    images += [model.render_rgb_batch(chunk[k : k + 1])[0] for k in range(len(chunk))]
            return images

    def selection_context(self, step: int, model) -> SelectionContext:
        """The typed context a selector sees for a round at `step`."""
        candidates = self.candidates
        return SelectionContext(
            step=step,
            round_index=len(self.history),
            active=list(self.active),
            candidates=candidates,
            num_to_pick=min(self.config.views_per_round, len(candidates)),
            cameras=self.train_dataset.cameras,
            image_names=self.image_names,
            model=model,
            render=lambda idx, short_side=self.config.selection_short_side: self.render_views(model, idx, short_side),
            # Derived from (seed, round) so a resumed run makes the same choices as an uninterrupted one.
            generator=torch.Generator().manual_seed(self.config.seed * 1_000_003 + len(self.history)),
            device=torch.device(model.device),
        )

    def run_round(self, step: int, model) -> Selection:
        """Ask the selector for views, make them active, and log the round."""
        test_psnr = self.test_psnr(model) if self.config.eval_each_round else None
        context = self.selection_context(step, model)
        if not context.candidates:
            raise SelectionError("no withheld views left to select from")
        start = time.perf_counter()
        selection = check_selection(self.selector.select(context), context)
        seconds = time.perf_counter() - start
        self.active = sorted(self.active + list(selection.indices))
        record = {
            "round": len(self.history) + 1,
            "step": int(step),
            "selector": self.config.selector,
            "chosen": [self.image_names[i] for i in selection.indices],
            "chosen_indices": [int(i) for i in selection.indices],
            "seconds": float(seconds),
            "num_active": len(self.active),
            "test_psnr_before": test_psnr,
            "reset": False,
            "scores": {self.image_names[i]: float(s) for i, s in selection.scores.items()},
            "work": {k: float(v) for k, v in selection.work.items()},
        }
        self.history.append(record)
        self.train_unseen_cameras = self.sample_train_cameras()
        CONSOLE.print(
            f"[bold green]View selection round {record['round']} at step {step}[/bold green]: "
            f"+ {', '.join(record['chosen'])} ({self.config.selector}, {seconds:.2f} s, {len(self.active)} active)"
        )
        writer.put_scalar("selection/seconds", seconds, step)
        writer.put_scalar("selection/num_active", len(self.active), step)
        self._log_chosen_render(model, selection.indices[0], step)
        self._log_scores_plot(selection, step)
        self.write_log()
        return selection

    def reset_model(self, step: int, model, optimizers) -> None:
        """Reset-after-add: the model back to its step-0 state and every schedule restarted at `step`."""
        from hpgs_ns.trainer import restart_schedules

        if optimizers is None or not hasattr(model, "reset_to_initial"):
            raise ActiveViewError("reset-after-add needs the hpgs model and the trainer's optimizers")
        before = model.num_points
        model.reset_to_initial(step, optimizers.optimizers)
        restart_schedules(optimizers)
        self.history[-1].update(
            reset=True, num_gaussians_before_reset=int(before), num_gaussians_after_reset=int(model.num_points)
        )
        CONSOLE.print(f"reset after add: {before} -> {model.num_points} Gaussians, schedules restart at step {step}")
        writer.put_scalar("selection/num_gaussians_before_reset", before, step)
        self.write_log()

    @torch.no_grad()
    def test_psnr(self, model) -> float:
        """Mean PSNR over the test views with the current splat (eval mode)."""
        from hpgs_ns.metrics import psnr

        with eval_mode(model):
            values = []
            for camera, batch in self.fixed_indices_eval_dataloader:
                rgb = model.get_outputs_for_camera(camera)["rgb"].clamp(0, 1)
                gt = batch["image"].float()
                gt = gt / 255.0 if batch["image"].dtype == torch.uint8 else gt
                values.append(psnr(rgb.cpu(), gt[..., :3].cpu()))
            return float(np.mean(values)) if values else float("nan")

    def _log_chosen_render(self, model, index: int, step: int) -> None:
        try:
            image = self.render_views(model, [index], self.config.selection_short_side)[0]
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

    def write_log(self) -> Optional[Path]:
        """Write `selected_views.json` in the run directory (temp file, then rename)."""
        if self.run_dir is None:
            return None
        initial = [i for i in self.active if all(i not in h["chosen_indices"] for h in self.history)]
        payload = {
            "selector": self.config.selector,
            "seed": self.config.seed,
            "reset_after_add": self.config.reset_after_add,
            "initial": [self.image_names[i] for i in initial],
            "rounds": self.history,
            "active": [self.image_names[i] for i in self.active],
            "withheld": [self.image_names[i] for i in self.candidates],
            "test": [Path(p).name for p in self.eval_dataset.image_filenames],
            "peak_gpu_memory_mb": torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None,
        }
        return write_json_atomic(self.run_dir / "selected_views.json", payload)


def farthest_point_order(points: torch.Tensor, k: int, start: int = 0, chosen: Sequence[int] = ()) -> List[int]:
    """Greedy farthest-point sampling: `k` indices of `points` [N, 3], each farthest from those already chosen
    (`chosen`, or `start` when none)."""
    points = points.double()
    picked = list(chosen) if chosen else [start]
    dist = torch.cdist(points, points[picked]).min(dim=1).values
    out = [] if chosen else [start]
    while len(out) < k and len(picked) < len(points):
        dist[picked] = -1
        nxt = int(torch.argmax(dist))
        picked.append(nxt)
        out.append(nxt)
        dist = torch.minimum(dist, torch.linalg.norm(points - points[nxt], dim=1))
    return out
