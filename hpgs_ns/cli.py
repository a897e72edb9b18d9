"""The `hpgs` console script: the project's own tools as tyro subcommands.

Each command is a dataclass with a `main()` method, defined in the module that does the work; this file only
lists them. Imports are lazy so `hpgs --help` stays fast: `hpgs --help` imports no command module (the one-line
summaries are kept here; tests/test_cli_imports.py checks they match the dataclasses' docstrings), and
`hpgs CMD --help` imports only CMD's module, whose module level imports neither torch nor nerfstudio (those are
imported where the work is done). tests/test_cli_imports.py checks both; benchmarks/help_time.py times them.
"""

from __future__ import annotations

import importlib
import sys
import warnings

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

# subcommand name -> the first line of its dataclass's docstring, for `hpgs --help` without importing the commands.
SUMMARIES = {
    "demo": "Generate the synthetic scene, train `hpgs` on it, and print the test metrics.",
    "make-scene": "Generate the embedded synthetic 360-degree scene (images, COLMAP model, ground truth).",
    "collect": "Train on a few random views and render every training camera periodically, for labelling.",
    "bench": "Benchmark selectors (test PSNR/SSIM/LPIPS, wall and selection time, memory) on scenes.",
    "train-pref": "Train a preference model (which render is worse) on labelled pairs; writes a small checkpoint.",
    "eval-pref": "Accuracy of a preference model on labelled pairs (which image of each pair is worse).",
    "label": "Label which render of each pair is worse: a browser page (keys 1/2/s/u), or an error oracle.",
    "suggest": "Suggest where to take the next photos of a capture, from a trained run.",
}


def _load(spec: str):
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


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
    lines = ["usage: hpgs {" + ",".join(COMMANDS) + "} ...", "", "Commands:"]
    lines += [f"  {name:<12} {SUMMARIES[name]}" for name in COMMANDS]
    return "\n".join(lines)


def entrypoint() -> None:
    """Run one `hpgs` subcommand."""
    from hpgs_ns.errors import install_excepthook

    install_excepthook()  # fixable failures print as one line
    quiet_third_party_warnings()
    argv = sys.argv[1:]
    # Build only the chosen subcommand's parser: importing every command (torch, nerfstudio) for --help is slow.
    if argv and argv[0] in COMMANDS:
        import tyro

        command = tyro.cli(_load(COMMANDS[argv[0]]), args=argv[1:], prog=f"hpgs {argv[0]}")
        command.main()
        return
    if argv and argv[0] not in ("-h", "--help"):
        print(f"hpgs: unknown command {argv[0]!r}; choose one of: {', '.join(COMMANDS)}", file=sys.stderr)
        sys.exit(2)
    print(usage())


if __name__ == "__main__":
    entrypoint()
