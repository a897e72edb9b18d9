"""The selector registry: every name `--pipeline.selection.selector` accepts, and where its config class is.

Built-in selectors are `BUILTIN_SELECTORS` below, one line each: name -> "module:ConfigClass", as `hpgs_ns.cli` lists
its commands. A new one is its module and one line here. Selectors of other packages register through the
`hpgs_ns.selectors` entry point group, so adding one needs no edit of this package; in the plugin's pyproject.toml:

    [project.entry-points."hpgs_ns.selectors"]
    my-selector = "my_package.selector:MySelectorConfig"

The entry point names a `SelectorConfig` subclass (or an instance of one, to set its options): its `setup()`
returns an object with `select(context) -> Selection` (`hpgs_ns.selectors.base`). Its typed fields become
`--pipeline.selection.<name>.<option>` flags like a built-in selector's (`selection.config` reads
`selector_classes` when it is imported); a plugin whose module cannot be imported is still listed, and choosing it
is the one-line error saying why.

This module is the one list of selectors: the selection config, the candidate log, `hpgs bench`'s defaults and
rows, provenance and the docs' tests read it. Importing it imports neither torch nor nerfstudio (nor tyro), so the
names, their order and the default are read for free (`hpgs bench --help`); a config class is imported when it is
asked for (`selector_class`, `selector_config`, `selector_classes`). A selector's facts (whether it uses a
preference model, its fitted options, its code files, ...) are its config class's variables (`SelectorConfig`'s),
in one place for built-in and other packages' selectors alike: reading them imports the class.
"""

from __future__ import annotations

import copy
import importlib
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Type

if TYPE_CHECKING:
    from hpgs_ns.selectors.base import SelectorConfig

ENTRY_POINT_GROUP = "hpgs_ns.selectors"
# Chosen by the rule docs/benchmark.md fixed before the twelve-scene matrix ran: `farthest` beat the paper's `hpgs`
# on both rankings (runs and final-sets). The paper's method is `--pipeline.selection.selector hpgs`.
DEFAULT_SELECTOR = "farthest"

# The built-in selectors, in the order the choices, `hpgs bench --selectors` and the tables list them.
BUILTIN_SELECTORS: Dict[str, str] = {
    "random": "hpgs_ns.selectors.random_views:RandomSelectorConfig",
    "farthest": "hpgs_ns.selectors.farthest:FarthestSelectorConfig",
    "fisher": "hpgs_ns.selectors.fisher:FisherSelectorConfig",
    "coverage": "hpgs_ns.selectors.coverage:CoverageSelectorConfig",
    "hpgs": "hpgs_ns.selectors.hpgs:HpgsSelectorConfig",
    "condorcet": "hpgs_ns.selectors.condorcet:CondorcetSelectorConfig",
    "blend": "hpgs_ns.selectors.blend:BlendSelectorConfig",
    # named combinations of the ones above (`hpgs_ns.selectors.presets`)
    "fisher-dopt": "hpgs_ns.selectors.presets:FisherDoptSelectorConfig",
    "farthest-dopt": "hpgs_ns.selectors.presets:FarthestDoptSelectorConfig",
}


def _entry_points() -> Dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name not in BUILTIN_SELECTORS}


def _selection_error(message: str) -> Exception:
    from hpgs_ns.selectors.base import SelectionError  # torch: only once a selector is asked for

    return SelectionError(message)


def option_group(name: str) -> str:
    """The field of `SelectionConfig` holding selector `name`'s options (`my-selector` -> `my_selector`)."""
    return name.replace("-", "_")


def selector_names() -> List[str]:
    """Built-in selectors in their usual order, then those registered by other packages (sorted)."""
    return list(BUILTIN_SELECTORS) + sorted(_entry_points())


def selector_class(name: str) -> Type[SelectorConfig]:
    """The config class of selector `name` (imported now): where its facts are (`SelectorConfig`'s class variables)."""
    if name in BUILTIN_SELECTORS:
        module, _, attr = BUILTIN_SELECTORS[name].partition(":")
        return getattr(importlib.import_module(module), attr)
    return type(selector_config(name))


def selector_classes() -> Dict[str, Type[SelectorConfig]]:
    """Every selector whose config class can be had: the built-in ones in order, then other packages' (imported
    now; one that fails to import is left out here and fails with one line when chosen)."""
    from hpgs_ns.selectors.base import SelectionError

    classes = {name: selector_class(name) for name in BUILTIN_SELECTORS}
    for name in sorted(_entry_points()):
        try:
            classes[name] = type(selector_config(name))
        except SelectionError:
            continue
    return classes


def selector_config(name: str) -> SelectorConfig:
    """A fresh config (default options) of selector `name`; one-line error for an unknown name or a broken
    entry point."""
    if name in BUILTIN_SELECTORS:
        return selector_class(name)()
    plugins = _entry_points()
    if name not in plugins:
        raise _selection_error(
            f"unknown selector {name!r}; choose one of {', '.join(selector_names())} "
            f"(other packages add selectors through the {ENTRY_POINT_GROUP!r} entry point group)"
        )
    try:
        target = plugins[name].load()
    except Exception as err:
        raise _selection_error(f"selector {name!r} ({plugins[name].value}) cannot be loaded: {err}") from err
    config = target() if isinstance(target, type) else copy.deepcopy(target)
    if not callable(getattr(config, "setup", None)):
        raise _selection_error(f"selector {name!r} ({plugins[name].value}) is not a SelectorConfig; its entry point "
                               "must name one")
    return config


def name_of(config_class: type) -> Optional[str]:
    """The name `config_class` is registered under (a built-in line or an entry point naming the class), without
    importing any other selector; None if none names it."""
    target = f"{config_class.__module__}:{config_class.__qualname__}"
    found = next((name for name, value in BUILTIN_SELECTORS.items() if value == target), None)
    if found is None:  # the entry points are read only for a class no built-in line names
        found = next((name for name, ep in sorted(_entry_points().items()) if ep.value.replace(" ", "") == target), None)
    return found


def __getattr__(name: str) -> Any:
    # `SelectorName`: every registered selector, built-in or from another package's entry point, as tyro shows the
    # choices. Made when first read (by `selection.config`), not at import: it needs tyro and the entry points, which
    # the names alone do not. A string, not a Literal: tyro would draw its own error box for an unknown name and
    # exit 2; `SelectionConfig` checks it instead (one line, `unknown selector`).
    if name == "SelectorName":
        import tyro
        from typing_extensions import Annotated

        globals()[name] = Annotated[str, tyro.conf.arg(metavar="{" + ",".join(selector_names()) + "}")]
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
