"""The strategy registry: every trainer strategy, name -> "module:ConfigClass" (as `hpgs_ns.selectors.registry`
lists the selectors). A new strategy is its module and one line here: the model config gets its option group
(`--pipeline.model.<name>.*`) and the model builds it and calls its hooks from this list.

Importing this module imports neither torch nor nerfstudio; a config class is imported when asked for."""

from __future__ import annotations

import importlib
from typing import Dict, Type

BUILTIN_STRATEGIES: Dict[str, str] = {
    "near-cull": "hpgs_ns.strategies.near_cull:NearCullConfig",
    "depth-loss": "hpgs_ns.strategies.depth_loss:DepthLossConfig",
    "restarts": "hpgs_ns.strategies.restarts:RestartsConfig",
}


def option_group(name: str) -> str:
    """The model config's field holding strategy `name`'s options (`depth-loss` -> `depth_loss`)."""
    return name.replace("-", "_")


def strategy_names():
    return list(BUILTIN_STRATEGIES)


def strategy_class(name: str) -> Type:
    """The config class of strategy `name` (imported now)."""
    module, _, attr = BUILTIN_STRATEGIES[name].partition(":")
    return getattr(importlib.import_module(module), attr)


def strategy_classes() -> Dict[str, Type]:
    return {name: strategy_class(name) for name in BUILTIN_STRATEGIES}
