"""nerfstudio's trainer with what `hpgs` runs need: resumes that end on time, and an optional final evaluation.

- A resumed run (`--load-dir`) ends at the configured total step count; stock nerfstudio runs another full
  `max_num_iterations` after the checkpoint's step.
- A config.yml written by hpgs-ns 0.1 (a VanillaPipeline, rounds inside the datamanager) is upgraded to the
  `hpgs` pipeline when it is trained again (`--load-config`), so its selection rounds still run.

`--final-eval-json PATH` writes what stock `ns-eval --output-path PATH` would write for the final checkpoint
(the same `get_average_eval_image_metrics(get_std=True)` call on the same weights) and each test view's metrics,
from the training process: it saves `ns-eval`'s ~15 s of start-up per run, which `hpgs bench` pays hundreds of times.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Type

from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns import schedules
from hpgs_ns.atomic_write import write_json_atomic
from hpgs_ns.pipeline import upgrade_pipeline_config

# config.yml files of hpgs-ns 0.1 name the scheduler classes here.
FloatExponentialDecaySchedulerConfig = schedules.FloatExponentialDecaySchedulerConfig
FloatExponentialDecayScheduler = schedules.FloatExponentialDecayScheduler


@dataclass
class HpgsTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig; resumed runs stop at `max_num_iterations` in total."""

    _target: Type = field(default_factory=lambda: HpgsTrainer)
    final_eval_json: Optional[Path] = None
    """If set, evaluate the test views once training ends and write `ns-eval`'s JSON here."""


class HpgsTrainer(Trainer):
    """nerfstudio's Trainer whose resumed runs end at the configured total step count."""

    config: HpgsTrainerConfig

    def __init__(self, config: HpgsTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        if upgrade_pipeline_config(config):
            CONSOLE.print("config.yml of hpgs-ns 0.1: its pipeline is now the hpgs pipeline (selection rounds run)")
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
        with cleanup:
            super().setup(test_mode=test_mode)

    def _load_checkpoint(self) -> None:
        super()._load_checkpoint()
        if self._start_step > 0:
            # nerfstudio's loop runs max_num_iterations steps after the checkpoint: make that the steps left.
            self.config.max_num_iterations = max(self.end_step - self._start_step, 0)
            self.step = self._start_step - 1  # what `_after_train` saves if nothing is left to run

    def _after_train(self) -> None:
        # Before the parent's part: with the viewer on, it never returns.
        if self.config.final_eval_json is not None:
            write_final_eval(self, Path(self.config.final_eval_json))
        super()._after_train()


def write_final_eval(trainer: Trainer, path: Path) -> Path:
    """`ns-eval`'s output for the trainer's current weights (what `_after_train` saves as the final checkpoint),
    plus each test view's own metrics (`test_views`: name, psnr, ssim, lpips, in the test split's order)."""
    pipeline = trainer.pipeline
    model = pipeline.model
    per_view: List[Dict[str, float]] = []
    score_view = model.get_image_metrics_and_images

    def recording(outputs, batch):
        metrics_dict, images = score_view(outputs, batch)
        per_view.append({k: float(v) for k, v in metrics_dict.items()})
        return metrics_dict, images

    # nerfstudio averages the views' metrics without returning them: record each as it is scored (this call only).
    model.get_image_metrics_and_images = recording
    try:
        metrics = pipeline.get_average_eval_image_metrics(step=trainer.step, get_std=True)
    finally:
        del model.get_image_metrics_and_images
    names = list(getattr(pipeline.datamanager, "test_view_names", []))
    test_views = [{"name": n, **m} for n, m in zip(names, per_view)] if len(names) == len(per_view) else []
    payload = {
        "experiment_name": trainer.config.experiment_name,
        "method_name": trainer.config.method_name,
        "checkpoint": str(trainer.checkpoint_dir / f"step-{trainer.step:09d}.ckpt"),
        "results": metrics,
        "test_views": test_views,
    }
    return write_json_atomic(path, payload)
