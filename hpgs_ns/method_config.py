"""The `hpgs` method for `ns-train`: splatfacto trained on a growing set of views picked by a selector.

Registered through the `nerfstudio.method_configs` entry point in pyproject.toml. The HP-GS protocol: 20 initial
views evenly spaced along the capture, one view added every 2000 steps, 15000 steps in all (7 additions), every
8th image (file-name order) held out for testing.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Sequence, Tuple

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from hpgs_ns.compat import MOVED_FROM_DATAMANAGER, MOVED_GROUPS
from hpgs_ns.datamanager import ActiveDatamanagerConfig
from hpgs_ns.errors import OptionError, install_excepthook
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

OLD_PREFIX = "--pipeline.datamanager."


def removed_spelling(argv: Sequence[str]) -> Tuple[List[str], List[str]]:
    """(the words of `argv` that set selection options the 0.2 way, `--pipeline.datamanager.selector X` or
    `...fisher.probes N`, with their values; the same in today's spelling, `--pipeline.selection.*`)."""
    old: List[str] = []
    new: List[str] = []
    i = 0
    while i < len(argv):
        arg, i = argv[i], i + 1
        name, eq, value = arg[len(OLD_PREFIX):].partition("=") if arg.startswith(OLD_PREFIX) else ("", "", "")
        head, dot, rest = name.partition(".")
        moved = MOVED_FROM_DATAMANAGER.get(head.replace("-", "_")) if not dot else (head if head in MOVED_GROUPS else None)
        if moved is None:
            continue
        old.append(arg)
        new.append(f"--pipeline.selection.{moved.replace('_', '-')}{dot}{rest}" + (f"={value}" if eq else ""))
        while not eq and i < len(argv) and not argv[i].startswith("--"):
            old.append(argv[i])
            new.append(argv[i])
            i += 1
    return old, new


def reject_removed_spelling(argv: Sequence[str]) -> None:
    """OptionError (one line, exit 1) for `ns-train hpgs` with selection options spelled the 0.2 way: tyro's own
    answer is a 39-line box that does not say where they went."""
    if len(argv) < 2 or argv[1] != "hpgs" or Path(argv[0]).name not in ("ns-train", "train.py"):
        return
    old, new = removed_spelling(argv[2:])
    if old:
        raise OptionError(f"{' '.join(old)}: the 0.2 spelling of the selection options, removed in 0.4; pass {' '.join(new)}")


# ns-train imports this module while it builds its command line, before tyro parses it: the one place that can.
reject_removed_spelling(sys.argv)


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
