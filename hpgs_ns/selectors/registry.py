"""The selector registry: every name `--pipeline.selection.selector` accepts, and its options.

Built-in selectors are listed here. Selectors of other packages register through the `hpgs_ns.selectors`
entry point group, so adding one needs no edit of this package; in the plugin's pyproject.toml:

    [project.entry-points."hpgs_ns.selectors"]
    my-selector = "my_package.selector:MySelectorConfig"

The entry point names a `SelectorConfig` subclass (or an instance of one, to set its options): its `setup()`
returns an object with `select(context) -> Selection` (`hpgs_ns.selectors.base`). Its typed fields become
`--pipeline.selection.<name>.<option>` flags like a built-in selector's (`selection.config` reads
`selector_classes` when it is imported); a plugin whose module cannot be imported is still listed, and choosing it
is the one-line error saying why.

This module is the one list of selectors: the selection config, `hpgs bench`'s defaults and the docs' table read it,
and a selector's facts are its config class's (`SelectorConfig`'s class variables), read from there.
"""

from __future__ import annotations

import copy
from importlib.metadata import entry_points
from typing import Dict, List, Type

import tyro
from typing_extensions import Annotated

from hpgs_ns.selectors.base import SelectionError, SelectorConfig
from hpgs_ns.selectors.blend import BlendSelectorConfig
from hpgs_ns.selectors.condorcet import CondorcetSelectorConfig
from hpgs_ns.selectors.farthest import FarthestSelectorConfig
from hpgs_ns.selectors.fisher import FisherSelectorConfig
from hpgs_ns.selectors.hpgs import HpgsSelectorConfig
from hpgs_ns.selectors.random_views import RandomSelectorConfig

ENTRY_POINT_GROUP = "hpgs_ns.selectors"
# Chosen by the rule docs/benchmark.md fixed before the twelve-scene matrix ran: `farthest` beat the paper's `hpgs`
# on both rankings (runs and final-sets). The paper's method is `--pipeline.selection.selector hpgs`.
DEFAULT_SELECTOR = "farthest"

BUILTIN_SELECTORS: Dict[str, Type[SelectorConfig]] = {
    "random": RandomSelectorConfig,
    "farthest": FarthestSelectorConfig,
    "fisher": FisherSelectorConfig,
    "hpgs": HpgsSelectorConfig,
    "condorcet": CondorcetSelectorConfig,
    "blend": BlendSelectorConfig,
}


def _entry_points() -> Dict[str, object]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name not in BUILTIN_SELECTORS}


def option_group(name: str) -> str:
    """The field of `SelectionConfig` holding selector `name`'s options (`my-selector` -> `my_selector`)."""
    return name.replace("-", "_")


def selector_classes() -> Dict[str, Type[SelectorConfig]]:
    """Every selector whose config class can be had: the built-in ones in order, then other packages' (imported
    now; one that fails to import is left out here and fails with one line when chosen)."""
    classes: Dict[str, Type[SelectorConfig]] = dict(BUILTIN_SELECTORS)
    for name in sorted(_entry_points()):
        try:
            classes[name] = type(selector_config(name))
        except SelectionError:
            continue
    return classes


def selector_names() -> List[str]:
    """Built-in selectors in their usual order, then those registered by other packages (sorted)."""
    return list(BUILTIN_SELECTORS) + sorted(_entry_points())


def selector_config(name: str) -> SelectorConfig:
    """A fresh config (default options) of selector `name`; one-line error for an unknown name or a broken
    entry point."""
    if name in BUILTIN_SELECTORS:
        return BUILTIN_SELECTORS[name]()
    plugins = _entry_points()
    if name not in plugins:
        raise SelectionError(
            f"unknown selector {name!r}; choose one of {', '.join(selector_names())} "
            f"(other packages add selectors through the {ENTRY_POINT_GROUP!r} entry point group)"
        )
    try:
        target = plugins[name].load()  # type: ignore[attr-defined]
    except Exception as err:
        raise SelectionError(f"selector {name!r} ({plugins[name].value}) cannot be loaded: {err}") from err  # type: ignore[attr-defined]
    config = target() if isinstance(target, type) else copy.deepcopy(target)
    if not callable(getattr(config, "setup", None)):
        raise SelectionError(f"selector {name!r} ({plugins[name].value}) is not a SelectorConfig; its entry point must name one")  # type: ignore[attr-defined]
    return config


# Every registered selector, built-in or from another package's entry point, as tyro shows the choices (read once,
# when this module is imported). A string, not a Literal: tyro would draw its own error box for an unknown name and
# exit 2; `SelectionConfig` checks it instead (one line, `unknown selector`).
SelectorName = Annotated[str, tyro.conf.arg(metavar="{" + ",".join(selector_names()) + "}")]


def selector_class(name: str) -> Type[SelectorConfig]:
    """The config class of selector `name`: where its facts are (`SelectorConfig`'s class variables)."""
    return BUILTIN_SELECTORS[name] if name in BUILTIN_SELECTORS else type(selector_config(name))
