"""View selectors. One file per selector; this registry maps `--pipeline.datamanager.selector` names to configs."""

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, Selector, check_selection
from hpgs_ns.selectors.condorcet import CondorcetSelectorConfig
from hpgs_ns.selectors.farthest import FarthestSelectorConfig
from hpgs_ns.selectors.fisher import FisherSelectorConfig
from hpgs_ns.selectors.hpgs import HpgsSelectorConfig
from hpgs_ns.selectors.random_views import RandomSelectorConfig

SELECTOR_CONFIGS = {
    "random": RandomSelectorConfig,
    "farthest": FarthestSelectorConfig,
    "fisher": FisherSelectorConfig,
    "hpgs": HpgsSelectorConfig,
    "condorcet": CondorcetSelectorConfig,
}

__all__ = [
    "SELECTOR_CONFIGS",
    "RandomSelectorConfig",
    "FarthestSelectorConfig",
    "FisherSelectorConfig",
    "HpgsSelectorConfig",
    "CondorcetSelectorConfig",
    "Selection",
    "SelectionContext",
    "SelectionError",
    "Selector",
    "check_selection",
]
