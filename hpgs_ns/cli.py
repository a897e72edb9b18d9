"""The `hpgs` console script: the project's own tools as tyro subcommands, and those other packages register.

Each command is a dataclass with a `main()` method, defined in the module that does the work; this file only
lists them (`COMMANDS`), and finds the commands other packages add through the `hpgs.commands` entry point group
(`hpgs bench` comes that way), so the plugin never imports those packages. Imports are lazy so `hpgs --help`
stays fast: `hpgs --help` imports no command module (the one-line summaries are kept with each `Command`, and a
test checks they match the dataclasses' docstrings), and `hpgs CMD --help` imports only CMD's module, whose module
level imports neither torch nor nerfstudio (those are imported where the work is done).
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings
from dataclasses import dataclass
from typing import Dict


@dataclass(frozen=True)
class Command:
    """One `hpgs` subcommand: its tyro dataclass (with a `main()` method) as "module:ClassName", imported only when
    the command runs, and the first line of that class's docstring, for `hpgs --help` without importing it."""

    target: str
    summary: str

    def load(self) -> type:
        module, name = self.target.split(":")
        return getattr(importlib.import_module(module), name)


# The plugin's own commands, in the order `hpgs --help` lists them.
COMMANDS: Dict[str, Command] = {
    "demo": Command("hpgs_ns.demo:Demo", "Generate the synthetic scene, train `hpgs` on it, and print the test metrics."),
    "make-scene": Command("hpgs_ns.scenes.synthetic:MakeScene",
                          "Generate the embedded synthetic 360-degree scene (images, COLMAP model, ground truth)."),
    "collect": Command("hpgs_ns.preference.collect:Collect",
                       "Train on a few random views and render every training camera periodically, for labelling."),
    "train-pref": Command("hpgs_ns.preference.train:TrainPref",
                          "Train a preference model (which render is worse) on labelled pairs; writes a small checkpoint."),
    "eval-pref": Command("hpgs_ns.preference.evaluate:EvalPref",
                         "Accuracy of a preference model on labelled pairs (which image of each pair is worse)."),
    "label": Command("hpgs_ns.preference.label_server:Label",
                     "Label which render of each pair is worse: a browser page (keys 1/2/s/u), or an error oracle."),
    "suggest": Command("hpgs_ns.suggest.command:Suggest", "Suggest where to take the next photos of a capture, from a trained run."),
}

ENTRY_POINT_GROUP = "hpgs.commands"
"""Other packages add `hpgs` commands here: an entry point `name = "module:attr"` naming a `Command`."""
COMMANDS_ENV = "HPGS_COMMANDS"
"""`name=module:attr[,name=module:attr...]`: commands of a package on PYTHONPATH but not pip-installed (so without
entry points), as nerfstudio's NERFSTUDIO_METHOD_CONFIGS does for methods."""

# Commands another package provides, named here only to say how to get one that is missing.
ELSEWHERE = {
    "bench": "the benchmark package, which registers it through the hpgs.commands entry points when installed: "
             f"pip install -e . in the project's checkout (or, not installed, {COMMANDS_ENV}=bench=MODULE:ATTR with it on "
             "PYTHONPATH)",
}


def registered_commands() -> Dict[str, Command]:
    """The commands other packages register (`ENTRY_POINT_GROUP`, then `COMMANDS_ENV`, which wins), without the
    plugin's own names (those always mean the plugin's command). Importing one imports only the light module that
    declares its `Command`, not the command's own module."""
    from importlib.metadata import entry_points

    specs = {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)}
    for item in filter(None, (part.strip() for part in os.environ.get(COMMANDS_ENV, "").split(","))):
        name, _, spec = item.partition("=")
        specs[name.strip()] = spec.strip()
    found: Dict[str, Command] = {}
    for name, spec in specs.items():
        if name in COMMANDS:
            continue
        module, _, attr = spec.partition(":")
        try:
            command = getattr(importlib.import_module(module), attr)
        except ModuleNotFoundError as err:  # registered by an install whose package has gone since: not registered
            if err.name and module.startswith(err.name):
                continue
            raise
        if not isinstance(command, Command):
            raise TypeError(f"the hpgs command {name!r} ({spec}) is a {type(command).__name__}, not a hpgs_ns.cli.Command")
        found[name] = command
    return found


def all_commands() -> Dict[str, Command]:
    """Every command `hpgs` offers here: the plugin's, then the registered ones."""
    return {**COMMANDS, **registered_commands()}


def quiet_third_party_warnings() -> None:
    """Hide the FutureWarnings that nerfstudio 1.1.5 sets off at import in recent torch (2.14 here), which say
    nothing a user of `hpgs` can act on: every command that loads a run, a dataparser or a selector imports
    nerfstudio, which decorates functions with `torch.jit.script` (nerfstudio/cameras/camera_utils.py; torch warns
    from torch.jit._script) and `torch.cuda.amp.custom_fwd`/`custom_bwd` (nerfstudio/field_components/activations.py).
    Only these messages from these modules are ignored: any other warning, ours or theirs, still prints. (`hpgs
    --help` and `hpgs CMD --help` import no nerfstudio, so they have nothing to hide.)"""
    warnings.filterwarnings(
        "ignore", message=r"`torch\.jit\.script` is deprecated", category=FutureWarning, module=r"torch\.jit\._script"
    )
    warnings.filterwarnings(
        "ignore", message=r"`torch\.cuda\.amp\.custom_(fwd|bwd)\(args\.\.\.\)` is deprecated", category=FutureWarning,
        module=r"nerfstudio\.field_components\.activations",
    )


def usage() -> str:
    """The text of `hpgs --help`."""
    commands = all_commands()
    lines = ["usage: hpgs {" + ",".join(commands) + "} ...", "", "Commands:"]
    lines += [f"  {name:<12} {command.summary}" for name, command in commands.items()]
    return "\n".join(lines)


def entrypoint() -> None:
    """Run one `hpgs` subcommand."""
    from hpgs_ns.errors import install_excepthook

    install_excepthook()  # fixable failures print as one line
    quiet_third_party_warnings()
    argv = sys.argv[1:]
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return
    # Build only the chosen subcommand's parser: importing every command (torch, nerfstudio) for --help is slow.
    name = argv[0]
    command = COMMANDS.get(name) or registered_commands().get(name)
    if command is None:
        if name in ELSEWHERE:
            print(f"hpgs {name} needs {ELSEWHERE[name]}", file=sys.stderr)
            sys.exit(1)
        print(f"hpgs: unknown command {name!r}; choose one of: {', '.join(all_commands())}", file=sys.stderr)
        sys.exit(2)
    import tyro

    tyro.cli(command.load(), args=argv[1:], prog=f"hpgs {name}").main()


if __name__ == "__main__":
    # `python -m hpgs_ns.cli`: run the importable module's entrypoint, so that the `Command` class the registered
    # commands are made of (they import hpgs_ns.cli) is the one it checks them against, not this __main__ copy's.
    import hpgs_ns.cli

    hpgs_ns.cli.entrypoint()
