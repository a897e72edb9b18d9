"""View selectors: one file per selector (a `SelectorConfig` and a class with `select(context) -> Selection`).

`registry` maps `--pipeline.selection.selector` names to their configs: the built-in ones, and those other
packages register through the `hpgs_ns.selectors` entry point group.
"""

from hpgs_ns.selectors.base import (
    Selection,
    SelectionContext,
    SelectionError,
    Selector,
    SelectorConfig,
    check_selection,
)
from hpgs_ns.selectors.blend import BlendSelectorConfig
from hpgs_ns.selectors.condorcet import CondorcetSelectorConfig
from hpgs_ns.selectors.farthest import FarthestSelectorConfig
from hpgs_ns.selectors.fisher import FisherSelectorConfig
from hpgs_ns.selectors.hpgs import HpgsSelectorConfig
from hpgs_ns.selectors.random_views import RandomSelectorConfig
from hpgs_ns.selectors.registry import BUILTIN_SELECTORS, ENTRY_POINT_GROUP, selector_config, selector_names

__all__ = [
    "BUILTIN_SELECTORS",
    "ENTRY_POINT_GROUP",
    "selector_config",
    "selector_names",
    "RandomSelectorConfig",
    "FarthestSelectorConfig",
    "FisherSelectorConfig",
    "HpgsSelectorConfig",
    "CondorcetSelectorConfig",
    "BlendSelectorConfig",
    "Selection",
    "SelectionContext",
    "SelectionError",
    "Selector",
    "SelectorConfig",
    "check_selection",
]
