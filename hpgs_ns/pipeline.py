"""The `hpgs` pipeline: nerfstudio's VanillaPipeline plus the selection loop (and `hpgs collect`'s snapshots).

The datamanager and the model are set up exactly as VanillaPipeline does; this class adds the selection loop
(`selection`, `--pipeline.selection.*`) and its training callbacks. They run before the model's own callbacks at
each step, so a round sees the model as the previous iteration left it. Rounds exist only when training
(`test_mode="val"`): `ns-eval` and `ns-viewer` open a run without setting up its selector.

`selection_view` shows the selection in nerfstudio's viewer (`hpgs_ns.viewer`); nerfstudio installs it when the
viewer is on, and each round redraws it.

When nerfstudio's `eval_setup` opens a run (`ns-eval`, `ns-viewer`, `ns-render`), it has chosen the checkpoint
folder from the output path saved in config.yml before it sets the pipeline up, and loads it after: a copied or
moved run folder would load the original's checkpoints, or none. `open_run_checkpoints` (run once the datamanager
and model are set up, so a damaged config.yml is named first) loads the ones beside the config.yml instead, saying
so in one line, and stops with one line when there are none.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Type

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns import compat
from hpgs_ns.errors import UserError
from hpgs_ns.selection.config import SelectionConfig
from hpgs_ns.selection.rounds import SelectionRounds
from hpgs_ns.selection.snapshots import Snapshots
from hpgs_ns.strategies.base import RunStart
from hpgs_ns.viewer import SelectionView


class RunFolderError(UserError, RuntimeError):
    """An opened run (`ns-eval`, `ns-viewer`) has no checkpoint to load."""


def _checkpoints(folder: Path) -> List[Path]:
    return sorted(folder.glob("step-*.ckpt")) if folder.is_dir() else []


def open_run_checkpoints(trainer_config, config_path: Path) -> None:
    """Point `trainer_config.load_dir` (what `eval_setup` loads from) at the checkpoints beside `config_path` when
    they are not the ones the config names (a copied or moved run folder; the config keeps the output path it was
    trained with), with one line saying which are loaded and why; RunFolderError when neither folder holds one."""
    named = Path(trainer_config.load_dir)
    own = Path(config_path).parent / trainer_config.relative_model_dir
    same = own.resolve() == named.resolve()
    if not same and _checkpoints(own):
        CONSOLE.print(f"[yellow]{config_path} names {named} as its checkpoints (the output path it was trained with); "
                      f"loading the ones beside it, in {own}", soft_wrap=True)
        trainer_config.load_dir = own
        return
    if _checkpoints(named):
        return
    elsewhere = "" if same else f", nor does {named}, the folder {Path(config_path).name} names"
    raise RunFolderError(f"no checkpoint to load: {own} holds no step-*.ckpt{elsewhere}; train the run first (it saves one "
                         "every --steps-per-save steps and at its last), or copy the run's nerfstudio_models there")


def _opening_run():
    """(TrainerConfig, config.yml path) of the run nerfstudio's `eval_setup` is opening, when it is the caller
    setting this pipeline up (its frame holds both: nerfstudio 1.1.5 offers no hook between choosing the
    checkpoint folder and loading it); None otherwise (training, a test building a pipeline)."""
    frame = sys._getframe(1)
    while frame is not None:
        code = frame.f_code
        if code.co_name == "eval_setup" and Path(code.co_filename).as_posix().endswith("nerfstudio/utils/eval_utils.py"):
            config, path = frame.f_locals.get("config"), frame.f_locals.get("config_path")
            return (config, Path(path)) if getattr(config, "load_dir", None) is not None and path is not None else None
        frame = frame.f_back
    return None


@dataclass
class HpgsPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline with next-best-view selection rounds."""

    _target: Type = field(default_factory=lambda: HpgsPipeline)
    selection: SelectionConfig = field(default_factory=SelectionConfig)
    """The selection loop: when rounds run, the selector and its options, what is recorded."""

    def __setstate__(self, state: dict) -> None:
        # PyYAML restores attributes, not __init__: a config.yml of 0.2 keeps its selection options elsewhere.
        compat.read_pipeline_state(self, state)


class HpgsPipeline(VanillaPipeline):
    """VanillaPipeline whose training adds the views a selector picks (`hpgs_ns.selection`)."""

    config: HpgsPipelineConfig

    def __init__(self, config: HpgsPipelineConfig, device: str, test_mode="val", *args, **kwargs):
        if getattr(config.model, "random_init", False) and getattr(config.datamanager, "seed_points", None) == "auto":
            config.datamanager.seed_points = "colmap"  # random-init asks for a random start: nothing to triangulate
        super().__init__(config, device, test_mode, *args, **kwargs)
        # after the datamanager and model are set up: a damaged config.yml fails there first, and is named as such
        opening = _opening_run() if test_mode != "val" else None
        if opening is not None:
            open_run_checkpoints(*opening)
        training = test_mode == "val"
        selection = config.selection
        signature = selection.resume_signature(self.datamanager.config.seed)
        # the start as resolved (`auto` is colmap or active); checkpoints without it: trainer.check_resume_matches
        signature["seed-points"] = str(getattr(self.datamanager, "seed_points_mode", "colmap"))
        dm = self.datamanager
        start = RunStart(seed_points=signature["seed-points"], split_cameras=dm.train_dataset.cameras,
                         active_cameras=lambda: dm.active_cameras, training=training)
        for name, strategy in getattr(self.model, "strategies_by_name", {}).items():
            kept = strategy.at_start(self.model, start)
            if isinstance(kept, dict):  # under keys of its own (the restarts: those checkpoints have always held)
                signature.update(kept)
            elif kept is not None:  # what a resumed run must keep (off: the signature stays as it was)
                signature[name] = kept
        self.datamanager.selection_signature = signature
        self.rounds: Optional[SelectionRounds] = selection.setup(datamanager=self.datamanager, model=self.model) if training else None
        self.snapshots: Optional[Snapshots] = Snapshots(selection.snapshot_every, self.datamanager, self.model) if training else None
        # A viewer element, not an nn.Module: checkpoints' keys stay the same.
        self.selection_view = SelectionView(self.datamanager)
        if self.rounds is not None:
            self.rounds.listeners.append(self.selection_view.on_round)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        attrs = training_callback_attributes
        # The trainer loads a checkpoint (--load-dir) after the viewer installed the view: show its rounds.
        self.selection_view.refresh()
        callbacks = self.datamanager.get_training_callbacks(attrs)
        if self.rounds is not None and self.snapshots is not None:
            callbacks += self.rounds.callbacks(attrs) + self.snapshots.callbacks(attrs)
        return callbacks + self.model.get_training_callbacks(attrs)
