"""The `hpgs` pipeline: nerfstudio's VanillaPipeline plus the selection rounds (and `hpgs collect`'s snapshots).

The datamanager and the model are set up exactly as VanillaPipeline does; this class only adds the rounds'
training callbacks. They run before the model's own callbacks at each step, so a round sees the model as the
previous iteration left it. Rounds exist only when training (`test_mode="val"`): `ns-eval` and `ns-viewer` open a
run without setting up its selector.

`selection_view` shows the selection in nerfstudio's viewer (`hpgs_ns.viewer`); nerfstudio installs it when the
viewer is on, and each round redraws it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Type

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig

from hpgs_ns.rounds import SelectionRounds
from hpgs_ns.snapshots import Snapshots
from hpgs_ns.viewer import SelectionView


@dataclass
class HpgsPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline with next-best-view selection rounds."""

    _target: Type = field(default_factory=lambda: HpgsPipeline)


class HpgsPipeline(VanillaPipeline):
    """VanillaPipeline whose training adds the views a selector picks (`hpgs_ns.rounds`)."""

    config: HpgsPipelineConfig

    def __init__(self, config: HpgsPipelineConfig, device: str, test_mode="val", *args, **kwargs):
        super().__init__(config, device, test_mode, *args, **kwargs)
        training = test_mode == "val"
        self.rounds: Optional[SelectionRounds] = SelectionRounds(self.datamanager, self.model) if training else None
        self.snapshots: Optional[Snapshots] = Snapshots(self.datamanager, self.model) if training else None
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


def upgrade_pipeline_config(config) -> bool:
    """Turn a config.yml of hpgs-ns 0.1 (a VanillaPipelineConfig, rounds inside the datamanager) into this
    pipeline's config, in place, so resuming it (`--load-config`) still runs the rounds. True if it changed."""
    from hpgs_ns.datamanager import ActiveDatamanagerConfig

    pipeline = config.pipeline
    if type(pipeline) is VanillaPipelineConfig and isinstance(pipeline.datamanager, ActiveDatamanagerConfig):
        config.pipeline = HpgsPipelineConfig(datamanager=pipeline.datamanager, model=pipeline.model)
        return True
    return False
