"""View selectors: one file per selector (a `SelectorConfig` and a class with `select(context) -> Selection`).

`registry` maps `--pipeline.selection.selector` names to their configs: the built-in ones, and those other
packages register through the `hpgs_ns.selectors` entry point group.

Importing this package imports nothing: `hpgs_ns.selectors.registry` (the names, no torch) is read by `hpgs bench
--help`. The names below, and every built-in selector's config class by its class name (`RandomSelectorConfig`,
...), are imported on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

_FROM = {
    "hpgs_ns.selectors.base": ("Selection", "SelectionContext", "SelectionError", "Selector", "SelectorConfig",
                               "check_selection"),
    "hpgs_ns.selectors.registry": ("BUILTIN_SELECTORS", "ENTRY_POINT_GROUP", "selector_config", "selector_names"),
}

__all__ = [name for names in _FROM.values() for name in names]


def __getattr__(name: str) -> Any:
    for module, names in _FROM.items():
        if name in names:
            return getattr(importlib.import_module(module), name)
    registry = importlib.import_module("hpgs_ns.selectors.registry")
    for target in registry.BUILTIN_SELECTORS.values():  # a built-in selector's config class
        module, _, attr = target.partition(":")
        if attr == name:
            return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
