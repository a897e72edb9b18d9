"""The `hpgs` method for `ns-train`: splatfacto trained on a growing set of views picked by a selector.

Registered through the `nerfstudio.method_configs` entry point in pyproject.toml. The HP-GS protocol: 20 initial
views evenly spaced along the capture, one view added every 2000 steps, 15000 steps in all (7 additions), every
8th image (file-name order) held out for testing.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import List, Optional

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from hpgs_ns.datamanager import ActiveDatamanagerConfig
from hpgs_ns.dataparser import DATAPARSERS
from hpgs_ns.errors import install_excepthook
from hpgs_ns.model import HpgsSplatfactoModelConfig
from hpgs_ns.pipeline import HpgsPipelineConfig
from hpgs_ns.schedules import FloatExponentialDecaySchedulerConfig
from hpgs_ns.trainer import HpgsTrainerConfig

TOTAL_STEPS = 15000

# nerfstudio imports this module for ns-train/ns-eval/ns-viewer: our fixable errors print as one line there.
install_excepthook()

OLD_PARSER_PREFIX = "--pipeline.datamanager.dataparser."


def old_dataparser_flags_hint(argv: List[str]) -> Optional[str]:
    """The command line in the new spelling when `argv` (an `ns-train hpgs` call) sets dataparser options the
    0.1 way (`--pipeline.datamanager.dataparser.X V`, which tyro rejects once the dataparser is a subcommand);
    None otherwise."""
    if not any(a.startswith(OLD_PARSER_PREFIX) for a in argv):
        return None
    kept: List[str] = []
    moved: List[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if not arg.startswith(OLD_PARSER_PREFIX):
            kept.append(arg)
            i += 1
            continue
        moved.append("--" + arg[len(OLD_PARSER_PREFIX):])
        i += 1
        while "=" not in arg and i < len(argv) and not argv[i].startswith("--"):
            moved.append(argv[i])
            i += 1
    parser = next((a for a in kept if a in DATAPARSERS), None)
    if parser is None:
        kept.append("mipnerf360")
        parser_at = len(kept)
    else:
        parser_at = kept.index(parser) + 1
    fixed = kept[:parser_at] + moved + kept[parser_at:]
    return "dataparser options now follow the dataparser subcommand: " + shlex.join(["ns-train", *fixed])


def _reject_old_dataparser_flags() -> None:
    # tyro's own message for them ("unrecognized arguments") does not say where they went; ns-train imports this
    # module before it parses its arguments, so this is the one place that can.
    if Path(sys.argv[0]).name in ("ns-train", "train.py") and "hpgs" in sys.argv[1:]:
        hint = old_dataparser_flags_hint(sys.argv[1:])
        if hint is not None:
            print(f"error: {hint}", file=sys.stderr)
            sys.exit(2)


_reject_old_dataparser_flags()


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
    description="HP-GS: splatfacto with next-best-view selection (human-preference, FisherRF, farthest, random)",
)
