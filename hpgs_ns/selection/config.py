"""The selection loop's options: `--pipeline.selection.*` on the `ns-train hpgs` command line.

Which views are active at step 0 (and the split) is the datamanager's business; when rounds run, which selector
scores the withheld views, and what the loop records, is this config's. `setup()` builds the loop
(`hpgs_ns.selection.rounds.SelectionRounds`).

Up to hpgs-ns 0.2 these options sat on the datamanager (`--pipeline.datamanager.selector`, ...): that spelling
still works, with a warning (`take_datamanager_options`), and config.yml files of 0.1 and 0.2 are read the same way.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Type

from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns.errors import check_option
from hpgs_ns.selection.after_add import AfterAddConfig
from hpgs_ns.selectors import (
    BlendSelectorConfig,
    CondorcetSelectorConfig,
    FarthestSelectorConfig,
    FisherSelectorConfig,
    HpgsSelectorConfig,
    RandomSelectorConfig,
    SelectorConfig,
    registry,
)
from hpgs_ns.selectors.registry import SelectorName, selector_names


def _rounds():
    from hpgs_ns.selection.rounds import SelectionRounds

    return SelectionRounds


@dataclass
class SelectionConfig(InstantiateConfig):
    """When selection rounds run, which selector picks the views, and what the loop records."""

    _target: Type = field(default_factory=_rounds)
    selector: SelectorName = "hpgs"
    """Which selector picks the next views (default: the paper's human-preference selector). Other packages add
    selectors through the `hpgs_ns.selectors` entry point group."""
    select_every: int = 2000
    """A selection round runs at steps select_every, 2*select_every, ... (never at step 0)."""
    select_at: Tuple[int, ...] = ()
    """Explicit round steps (e.g. FisherRF's 400 900 1500 ...); when given, select-every is ignored."""
    views_per_round: int = 1
    """Views added per round (greedy batch selection when > 1)."""
    max_rounds: int = 7
    """Rounds before selection stops (HP-GS: 7 additions over 15000 steps)."""
    # One option group per built-in selector (registry.BUILTIN_SELECTORS); plugins' options come from the registry.
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
    blend: BlendSelectorConfig = field(default_factory=BlendSelectorConfig)
    """Options of the `blend` selector (farthest + hpgs, weights fitted on candidate logs)."""
    eval_each_round: bool = False
    """Measure test-view PSNR just before each round (recorded in selected_views.json; used by `hpgs bench`)."""
    stop_when_gain_below: Optional[float] = None
    """Stop selecting once the next view's predicted test-PSNR gain (dB) is below this (`hpgs_ns.selection.early_stop`;
    default: every round runs): views a scene does not need are not added."""
    gain_model: Optional[Path] = None
    """The gain calibration for stop-when-gain-below (`benchmarks/early_stop.py --write-model`; default:
    hpgs_ns/assets/gain-model.json, fitted on the suite's FisherRF-protocol runs)."""
    log_candidate_scores: bool = False
    """After each round, log every registered selector's score of every candidate and each candidate's render error
    against its withheld photo to candidate_scores.jsonl (analysis only: never read by the run, and its random
    stream is left as it was)."""
    snapshot_every: int = 0
    """If > 0, every this many steps (and at the last step) render every training-split view to
    `<run dir>/snapshots/step-NNNNNN/` (what `hpgs collect` labels). Test views are never rendered."""
    render_short_side: Optional[int] = None
    """Default render size (short side, pixels) for selectors that render views; None = dataset resolution."""
    after_add: AfterAddConfig = field(default_factory=AfterAddConfig)
    """How training reacts to the views a round adds (`hpgs_ns.selection.after_add`): refinement window, opacity
    reset, learning-rate rewind. All off: 0.3's schedule, keyed to step 0."""
    reset_after_add: bool = False
    """After each round, start training over from the new view set, as FisherRF (Jiang et al., ECCV 2024) does:
    the Gaussians go back to the step-0 ones, optimizer moments, densification state and camera optimizer are
    cleared, and learning rates and splatfacto's step-keyed schedule (densification, opacity reset, SH degree,
    resolution) restart at the round's step. The trainer's step keeps counting; the run ends at
    max-num-iterations."""

    def __setstate__(self, state: dict) -> None:
        # A config.yml written before an option existed (PyYAML restores attributes, not __init__): its default.
        self.__dict__.update(state)
        for f in fields(self):
            if f.name not in state and f.default_factory is not MISSING:
                setattr(self, f.name, f.default_factory())

    def __post_init__(self) -> None:
        # tyro builds this config while it parses the command line: a value that makes no sense is a one-line error
        # before nerfstudio prints the config or makes a run folder. (A config.yml is read without __init__.)
        self.check_values()

    def check_values(self, given_as: Optional[Dict[str, str]] = None) -> None:
        """Raise `OptionError` naming the first option whose value makes no sense, by its flag. `given_as`: option
        name -> the flag it was given as (the 0.2 spelling's, for values moved here); only those are checked then."""
        for name, (ok, need, fix) in VALUE_RULES.items():
            value = getattr(self, name)
            if value is not None and (given_as is None or name in given_as):
                flag = (given_as or {}).get(name, f"--pipeline.selection.{name.replace('_', '-')}")
                check_option(flag, value, ok(value), need, fix)

    def selector_config(self, name: Optional[str] = None) -> SelectorConfig:
        """The options of selector `name` (default: the chosen one): its group above for a built-in one, else the
        registry's defaults."""
        name = self.selector if name is None else name
        own = getattr(self, name, None)
        return own if isinstance(own, SelectorConfig) else registry.selector_config(name)

    def resume_signature(self, seed: int) -> Dict[str, str]:
        """What a resumed run must keep from its checkpoint ({option: value as text}): the selector, its options,
        the seed and the round schedule. max-rounds and the step count may grow (a longer run adds rounds)."""
        signature = {"selector": str(self.selector), "seed": str(int(seed)), "select-every": str(self.select_every),
                     "select-at": str(list(self.select_at)), "views-per-round": str(self.views_per_round),
                     "reset-after-add": str(bool(self.reset_after_add)), "after-add": self.after_add.describe()}
        options = self.selector_config()
        for f in fields(options):
            if not f.name.startswith("_"):
                signature[f"{self.selector}.{f.name.replace('_', '-')}"] = str(getattr(options, f.name))
        return signature


# Numeric options' sensible values: name -> (test, what the value must be, the fix).
VALUE_RULES = {
    "selector": (lambda v: v in selector_names(), "unknown selector",
                 "choose one of " + ", ".join(selector_names()) + " (or install the package that registers it)"),
    "select_every": (lambda v: v >= 0, "must be >= 0 (a round every this many steps)",
                     "pass 0 for no periodic rounds, or --pipeline.selection.select-at STEP ..."),
    "select_at": (lambda v: all(s >= 1 for s in v), "round steps must be >= 1 (no round runs at step 0)",
                  "drop the steps below 1"),
    "views_per_round": (lambda v: v >= 1, "must be at least 1 (the views each round adds)",
                        "pass 1 or more (--pipeline.selection.max-rounds 0 runs no rounds)"),
    "max_rounds": (lambda v: v >= 0, "must be >= 0", "pass 0 for no rounds"),
    "stop_when_gain_below": (lambda v: math.isfinite(v), "must be a finite number of dB",
                             "pass e.g. 0.05, or leave it out to run every round"),
    "snapshot_every": (lambda v: v >= 0, "must be >= 0", "pass 0 for no snapshots"),
    "render_short_side": (lambda v: v >= 1, "must be at least 1 pixel", "leave it out to render at the dataset's resolution"),
}

# Options that moved from the datamanager to `--pipeline.selection` in 0.3: old name -> new name.
MOVED_FROM_DATAMANAGER: Dict[str, str] = {
    **{name: name for name in ("selector", "select_every", "select_at", "views_per_round", "max_rounds",
                               "eval_each_round", "stop_when_gain_below", "gain_model", "log_candidate_scores",
                               "snapshot_every", "reset_after_add")},
    "selection_short_side": "render_short_side",
}
MOVED_GROUPS: Tuple[str, ...] = tuple(registry.BUILTIN_SELECTORS)


def take_datamanager_options(datamanager: Any, selection: SelectionConfig, warn: bool = True) -> Dict[str, str]:
    """Move the selection options set on the datamanager (the 0.2 spelling, or a 0.1/0.2 config.yml) into
    `selection`, leaving the datamanager's copies unset. Returns {old flag: new flag} of what moved; warns once per
    call when `warn` (a command line or script in the old spelling)."""
    moved: Dict[str, str] = {}
    given_as: Dict[str, str] = {}
    for old, new in MOVED_FROM_DATAMANAGER.items():
        value = getattr(datamanager, old, None)
        if value is None:
            continue
        setattr(selection, new, value)
        setattr(datamanager, old, None)
        moved[f"--pipeline.datamanager.{old.replace('_', '-')}"] = f"--pipeline.selection.{new.replace('_', '-')}"
        given_as[new] = f"--pipeline.datamanager.{old.replace('_', '-')}"
    for group in MOVED_GROUPS:
        value = getattr(datamanager, group, None)
        # The datamanager keeps a default group (tyro needs one to parse the old flags); only a changed one moves.
        if isinstance(value, SelectorConfig) and value != type(value)():
            setattr(selection, group, value)
            setattr(datamanager, group, type(value)())
            moved[f"--pipeline.datamanager.{group}.*"] = f"--pipeline.selection.{group}.*"
    if moved and warn:
        selection.check_values(given_as)  # the values given in the old spelling, named as given
        spelled = ", ".join(f"{old} -> {new}" for old, new in moved.items())
        CONSOLE.print(f"[yellow]deprecated option spelling (hpgs-ns 0.3 moved the selection options): {spelled}",
                      soft_wrap=True)
    return moved


def selection_field_names() -> Tuple[str, ...]:
    return tuple(f.name for f in fields(SelectionConfig) if f.name != "_target")
