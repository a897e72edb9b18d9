"""The `hpgs` method for `ns-train`: splatfacto trained on a growing set of views picked by a selector.

Registered through the `nerfstudio.method_configs` entry point in pyproject.toml. The HP-GS protocol: 20 initial
views evenly spaced along the capture, one view added every 2000 steps, 15000 steps in all (7 additions), every
8th image (file-name order) held out for testing.
"""

from __future__ import annotations

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from hpgs_ns.datamanager import ActiveDatamanagerConfig
from hpgs_ns.errors import install_excepthook
from hpgs_ns.model import HpgsSplatfactoModelConfig
from hpgs_ns.pipeline import HpgsPipelineConfig
from hpgs_ns.run_config import explain_load_config_failure
from hpgs_ns.schedules import FloatExponentialDecaySchedulerConfig
from hpgs_ns.selection.config import SelectionConfig
from hpgs_ns.trainer import HpgsTrainerConfig

TOTAL_STEPS = 15000

# nerfstudio imports this module for ns-train/ns-eval/ns-viewer: our fixable errors print as one line there, and
# so does nerfstudio's failure to read a damaged --load-config.
install_excepthook(explain=explain_load_config_failure)


def hpgs_trainer_config(max_steps: int = TOTAL_STEPS) -> HpgsTrainerConfig:
    """Splatfacto's optimizers with schedules sized to `max_steps`, and the active datamanager."""
    return HpgsTrainerConfig(
        method_name="hpgs",
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=max_steps,
        mixed_precision=False,
        machine=MachineConfig(device_type="cuda" if torch.cuda.is_available() else "cpu"),
        pipeline=HpgsPipelineConfig(
            datamanager=ActiveDatamanagerConfig(),
            model=HpgsSplatfactoModelConfig(),
            selection=SelectionConfig(),
        ),
        optimizers={
            "means": {
                "optimizer": AdamOptimizerConfig(lr=1.6e-4, eps=1e-15),
                "scheduler": FloatExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max_steps),
            },
            "features_dc": {"optimizer": AdamOptimizerConfig(lr=0.0025, eps=1e-15), "scheduler": None},
            "features_rest": {"optimizer": AdamOptimizerConfig(lr=0.0025 / 20, eps=1e-15), "scheduler": None},
            "opacities": {"optimizer": AdamOptimizerConfig(lr=0.05, eps=1e-15), "scheduler": None},
            "scales": {"optimizer": AdamOptimizerConfig(lr=0.005, eps=1e-15), "scheduler": None},
            "quats": {"optimizer": AdamOptimizerConfig(lr=0.001, eps=1e-15), "scheduler": None},
            "camera_opt": {
                "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
                "scheduler": FloatExponentialDecaySchedulerConfig(
                    lr_final=5e-7, max_steps=max_steps, warmup_steps=1000, lr_pre_warmup=0
                ),
            },
            "bilateral_grid": {
                "optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15),
                "scheduler": FloatExponentialDecaySchedulerConfig(
                    lr_final=1e-4, max_steps=max_steps, warmup_steps=1000, lr_pre_warmup=0
                ),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


hpgs = MethodSpecification(
    config=hpgs_trainer_config(),
    description="HP-GS: splatfacto with next-best-view selection (farthest by default; human-preference, FisherRF, random, ...)",
)
