"""Snapshots for `hpgs collect`: every `snapshot_every` steps, render every training-split view to disk.

`<run dir>/snapshots/step-NNNNNN/` holds one PNG per training-split camera (test views never: their photos must
not leak into labels) and `views.json` (which views were active). Each folder is written under a temporary name
and renamed into place, so a killed run leaves no half-written snapshot.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation

from hpgs_ns.atomic_write import write_json_atomic
from hpgs_ns.selection.schedule import Every, run_steps


class Snapshots:
    """Writes the snapshots of one training run (`--pipeline.selection.snapshot-every N`)."""

    def __init__(self, every: int, datamanager, model) -> None:
        self.datamanager = datamanager
        self.model = model
        self.every = int(every)
        self.schedule = Every(self.every)
        self.run_dir: Optional[Path] = None

    def callbacks(self, attrs: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """Snapshots every `every` steps (after that step's selection round) and after the last step."""
        if self.every <= 0:
            return []
        trainer = attrs.trainer
        if trainer is not None and getattr(trainer, "base_dir", None) is not None:
            self.run_dir = Path(trainer.base_dir)

        def before_iteration(step: int) -> None:
            if step in self.schedule:
                self.write(step)

        callbacks = [TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before_iteration)]
        if trainer is not None:
            _, end = run_steps(trainer)

            def after_training(step: int) -> None:
                if step + 1 in self.schedule:
                    self.write(step + 1)

            callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after_training, iters=(end - 1,)))
        return callbacks

    def write(self, step: int) -> Optional[Path]:
        """Render every training-split view at `step` into `snapshots/step-NNNNNN/` (temp folder, then rename)."""
        if self.run_dir is None:
            return None
        from PIL import Image

        dm = self.datamanager
        target = self.run_dir / "snapshots" / f"step-{step:06d}"
        if target.exists():
            return target
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".snapshot-", dir=target.parent))
        cameras = dm.train_dataset.cameras
        for i in range(len(dm.train_dataset)):
            image = self.model.render_views(cameras[torch.tensor([i], dtype=torch.long)])[0]
            array = (image.cpu().numpy() * 255 + 0.5).astype(np.uint8)
            Image.fromarray(array).save(tmp / f"{Path(dm.image_names[i]).stem}.png")
        write_json_atomic(tmp / "views.json", {"step": step, "active": [dm.image_names[i] for i in dm.active]})
        tmp.rename(target)
        return target
