"""The selection loop's options: `--pipeline.selection.*` on the `ns-train hpgs` command line.

Which views are active at step 0 (and the split) is the datamanager's business; when rounds run, which selector
scores the withheld views, and what the loop records, is this config's. `setup()` builds the loop
(`hpgs_ns.selection.rounds.SelectionRounds`). Each registered selector, built-in or another package's, has its
option group here (`--pipeline.selection.<name>.*`), made from the registry (`selectors.registry.selector_classes`).
config.yml files of hpgs-ns 0.1 and 0.2 kept these options on the datamanager: `hpgs_ns.compat` reads them.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Type

from nerfstudio.configs.base_config import InstantiateConfig

from hpgs_ns.errors import check_option
from hpgs_ns.resume_keys import resume, signature_of
from hpgs_ns.selectors import SelectorConfig, registry
from hpgs_ns.selectors.registry import DEFAULT_SELECTOR, SelectorName, option_group, selector_names


def _rounds():
    from hpgs_ns.selection.rounds import SelectionRounds

    return SelectionRounds


@dataclass
class SelectionLoopConfig(InstantiateConfig):
    """When selection rounds run, which selector picks the views, and what the loop records (`SelectionConfig`
    adds one option group per registered selector)."""

    _target: Type = field(default_factory=_rounds)
    selector: SelectorName = field(default=DEFAULT_SELECTOR, metadata=resume())
    """Which selector picks the next views (default: `farthest`, which beat the paper's human-preference selector `hpgs`
    on the twelve-scene benchmark, docs/results.md). Other packages add selectors through the `hpgs_ns.selectors`
    entry point group."""
    select_every: int = field(default=2000, metadata=resume())
    """A selection round runs at steps select_every, 2*select_every, ... (never at step 0)."""
    select_at: Tuple[int, ...] = field(default=(), metadata=resume(lambda v: str(list(v))))
    """Explicit round steps (e.g. FisherRF's 400 900 1500 ...); when given, select-every is ignored."""
    views_per_round: int = field(default=1, metadata=resume())
    """Views added per round (greedy batch selection when > 1)."""
    shortlist: Optional[SelectorName] = None
    """A selector that keeps its best shortlist-size share of the candidates each round; the chosen selector then
    ranks only those (e.g. `--pipeline.selection.shortlist farthest --pipeline.selection.selector fisher`). The
    shortlisting selector's options are its own group's. Default: the chosen selector ranks every candidate."""
    shortlist_size: float = 0.2
    """With shortlist: the share of the candidates it keeps (0 < share <= 1; at least one view)."""
    max_rounds: int = 7
    """Rounds before selection stops (HP-GS: 7 additions over 15000 steps)."""
    eval_each_round: bool = False
    """Measure test-view PSNR just before each round (recorded in selected_views.json; used by `hpgs bench`)."""
    stop_when_gain_below: Optional[float] = None
    """Stop selecting once the next view's predicted test-PSNR gain (dB) is below this (`hpgs_ns.selection.early_stop`;
    default: every round runs): views a scene does not need are not added."""
    gain_model: Optional[Path] = None
    """The gain calibration for stop-when-gain-below (a JSON gain model; default: the shipped
    hpgs_ns/assets/gain-model.json, fitted on benchmark runs of the FisherRF protocol)."""
    log_candidate_scores: bool = False
    """After each round, log every registered selector's score of every candidate and each candidate's render error
    against its withheld photo to candidate_scores.jsonl (analysis only: never read by the run, and its random
    stream is left as it was)."""
    snapshot_every: int = 0
    """If > 0, every this many steps (and at the last step) render every training-split view to
    `<run dir>/snapshots/step-NNNNNN/` (what `hpgs collect` labels). Test views are never rendered."""
    render_short_side: Optional[int] = None
    """Default render size (short side, pixels) for selectors that render views; None = dataset resolution."""

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

    def check_values(self) -> None:
        """Raise `OptionError` naming the first option whose value makes no sense, by its flag."""
        for name, (ok, need, fix) in VALUE_RULES.items():
            value = getattr(self, name)
            if value is not None:
                check_option(f"--pipeline.selection.{name.replace('_', '-')}", value, ok(value), need, fix)

    def build_selector(self):
        """The run's selector: the chosen one, ranking the shortlist's share of the candidates when `shortlist` is
        set (never under a uniform baseline such as `random`: `shortlist_notes` says so at start)."""
        chosen = self.selector_config().setup()
        if not self.uses_shortlist():
            return chosen
        from hpgs_ns.selectors.shortlist import ShortlistSelector

        return ShortlistSelector(self.selector_config(self.shortlist).setup(), chosen, self.shortlist_size, self.shortlist)

    def uses_shortlist(self) -> bool:
        """Whether a shortlist ranks this run's candidates: one is set and the selector ranks one."""
        return self.shortlist is not None and self.selector_config().ranks_a_shortlist

    def shortlist_notes(self) -> List[str]:
        """Start-up lines for shortlist options that change nothing in this run."""
        if self.shortlist is None:
            if self.shortlist_size != SelectionLoopConfig.shortlist_size:
                return [f"--pipeline.selection.shortlist-size {self.shortlist_size:g} does nothing in this run: no "
                        "shortlist (add --pipeline.selection.shortlist NAME)"]
            return []
        if not self.selector_config().ranks_a_shortlist:
            return [f"--pipeline.selection.shortlist {self.shortlist} changes nothing in this run: the selector is "
                    f"{self.selector}, which picks uniformly from every candidate (it is the baseline)"]
        if self.shortlist_size >= 1:
            return [f"--pipeline.selection.shortlist {self.shortlist} changes nothing in this run: shortlist-size 1 "
                    "keeps every candidate"]
        return []

    def selector_config(self, name: Optional[str] = None) -> SelectorConfig:
        """The options of selector `name` (default: the chosen one): its group above for a built-in one, else the
        registry's defaults."""
        name = self.selector if name is None else name
        own = getattr(self, option_group(name), None)
        return own if isinstance(own, SelectorConfig) else registry.selector_config(name)

    def idle_selector_options(self) -> List[str]:
        """The flags set away from their defaults on selectors this run does not use (e.g. `hpgs.model` while the
        selector is `farthest`): they change nothing, which the run says at start. The candidate log reads every
        selector's options, so with it none is idle."""
        if self.log_candidate_scores:
            return []
        idle = []
        for name in selector_names():
            group = getattr(self, option_group(name), None)
            if name in (self.selector, self.shortlist) or not isinstance(group, SelectorConfig):
                continue
            default = registry.selector_config(name)
            idle += [f"--pipeline.selection.{name}.{f.name.replace('_', '-')}" for f in fields(group)
                     if not f.name.startswith("_") and getattr(group, f.name) != getattr(default, f.name, None)]
        return idle

    def idle_selector_notes(self) -> List[str]:
        """Start-up lines for `idle_selector_options` (none when every option set belongs to a selector in use)."""
        idle = self.idle_selector_options()
        if not idle:
            return []
        owners = sorted({flag.split(".")[2] for flag in idle})
        fix = (f"add --pipeline.selection.selector {owners[0]}" if len(owners) == 1 else
               f"--pipeline.selection.selector picks one of {', '.join(owners)}")
        return [f"{', '.join(idle)} {'does' if len(idle) == 1 else 'do'} nothing in this run: the selector is "
                f"{self.selector} ({fix})"]

    def resume_signature(self, seed: int) -> Dict[str, str]:
        """What a resumed run must keep from its checkpoint ({option: value as text}): the selector, its options,
        the seed and the round schedule. max-rounds and the step count may grow (a longer run adds rounds)."""
        signature = {"seed": str(int(seed)), **signature_of(self)}  # the fields marked `resume()`
        used = [self.selector]
        if self.uses_shortlist():  # keys only when set: older checkpoints match
            signature.update({"shortlist": str(self.shortlist), "shortlist-size": str(self.shortlist_size)})
            used.append(self.shortlist)
        for name in dict.fromkeys(used):
            signature.update(_option_texts(name, self.selector_config(name)))
        return signature


def _option_texts(prefix: str, options) -> Dict[str, str]:
    """{"PREFIX.option": value as text} for a selector's options; a preset's parts' options as "PREFIX.part.option"."""
    out = {}
    for f in fields(options):
        if f.name.startswith("_"):
            continue
        value, key = getattr(options, f.name), f"{prefix}.{f.name.replace('_', '-')}"
        out.update(_option_texts(key, value) if isinstance(value, SelectorConfig) else {key: str(value)})
    return out


# Numeric options' sensible values: name -> (test, what the value must be, the fix).
VALUE_RULES = {
    "selector": (lambda v: v in selector_names(), "unknown selector",
                 "choose one of " + ", ".join(selector_names()) + " (or install the package that registers it)"),
    "select_every": (lambda v: v >= 0, "must be >= 0 (a round every this many steps)",
                     "pass 0 for no periodic rounds, or --pipeline.selection.select-at STEP ..."),
    "select_at": (lambda v: all(s >= 1 for s in v), "round steps must be >= 1 (no round runs at step 0)",
                  "drop the steps below 1"),
    "shortlist": (lambda v: v in selector_names(), "unknown selector",
                  "choose one of " + ", ".join(selector_names()) + " (or install the package that registers it)"),
    "shortlist_size": (lambda v: math.isfinite(v) and 0 < v <= 1, "must be a share of the candidates in (0, 1]",
                       "pass e.g. 0.2 (the best 20%)"),
    "views_per_round": (lambda v: v >= 1, "must be at least 1 (the views each round adds)",
                        "pass 1 or more (--pipeline.selection.max-rounds 0 runs no rounds)"),
    "max_rounds": (lambda v: v >= 0, "must be >= 0", "pass 0 for no rounds"),
    "stop_when_gain_below": (lambda v: math.isfinite(v), "must be a finite number of dB",
                             "pass e.g. 0.05, or leave it out to run every round"),
    "snapshot_every": (lambda v: v >= 0, "must be >= 0", "pass 0 for no snapshots"),
    "render_short_side": (lambda v: v >= 1, "must be at least 1 pixel", "leave it out to render at the dataset's resolution"),
}



def _option_groups():
    """(field, config class, default) for every registered selector: an entry point naming an instance of its config
    (options set) is that instance's copy."""
    builtin = registry.BUILTIN_SELECTORS
    return [(option_group(name), cls, field(default_factory=cls if name in builtin else
                                            (lambda name=name: registry.selector_config(name))))
            for name, cls in registry.selector_classes().items()]


# The loop's options and one group per selector, e.g. `--pipeline.selection.fisher.probes 8`. Made once, when this
# module is imported: the registry is the one list of selectors, so a new one (built-in or an entry point) needs no
# edit here. Its name and module are a plain class's, so config.yml files name it as `SelectionConfig`.
SelectionConfig = make_dataclass(
    "SelectionConfig", _option_groups(), bases=(SelectionLoopConfig,),
    namespace={"__module__": __name__, "__doc__": SelectionLoopConfig.__doc__.split(" (`SelectionConfig`")[0] + "."},
)
