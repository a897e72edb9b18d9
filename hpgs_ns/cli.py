"""The `hpgs` console script: the project's own tools as tyro subcommands.

Each command is a dataclass with a `main()` method, defined in the module that does the work; this file only
lists them. Imports are lazy so `hpgs --help` stays fast.
"""

from __future__ import annotations

import importlib
import sys

import tyro

# subcommand name -> "module:DataclassName"
COMMANDS = {
    "demo": "hpgs_ns.demo:Demo",
    "make-scene": "hpgs_ns.scenes.synthetic:MakeScene",
    "collect": "hpgs_ns.preference.collect:Collect",
    "bench": "hpgs_ns.bench.runs:Bench",
    "train-pref": "hpgs_ns.preference.train:TrainPref",
    "eval-pref": "hpgs_ns.preference.evaluate:EvalPref",
    "label": "hpgs_ns.preference.label_server:Label",
    "suggest": "hpgs_ns.suggest.command:Suggest",
}


def _load(spec: str):
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


def entrypoint() -> None:
    """Run one `hpgs` subcommand."""
    from hpgs_ns.errors import install_excepthook

    install_excepthook()  # fixable failures print as one line
    argv = sys.argv[1:]
    # Build only the chosen subcommand's parser: importing every command (torch, nerfstudio) for --help is slow.
    if argv and argv[0] in COMMANDS:
        command = tyro.cli(_load(COMMANDS[argv[0]]), args=argv[1:], prog=f"hpgs {argv[0]}")
        command.main()
        return
    if argv and argv[0] not in ("-h", "--help"):
        print(f"hpgs: unknown command {argv[0]!r}; choose one of: {', '.join(COMMANDS)}", file=sys.stderr)
        sys.exit(2)
    print("usage: hpgs {" + ",".join(COMMANDS) + "} ...\n\nCommands:")
    for name, spec in COMMANDS.items():
        doc = (_load(spec).__doc__ or "").strip().splitlines()
        print(f"  {name:<12} {doc[0] if doc else ''}")


if __name__ == "__main__":
    entrypoint()
