"""View selectors. One file per selector; this registry maps `--pipeline.datamanager.selector` names to configs."""

from hpgs_ns.selectors.base import Selection, SelectionContext, SelectionError, Selector, check_selection
from hpgs_ns.selectors.random_views import RandomSelectorConfig

SELECTOR_CONFIGS = {
    "random": RandomSelectorConfig,
}

__all__ = [
    "SELECTOR_CONFIGS",
    "RandomSelectorConfig",
    "Selection",
    "SelectionContext",
    "SelectionError",
    "Selector",
    "check_selection",
]
