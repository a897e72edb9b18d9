"""A training run's `config.yml`, read with one-line errors: `hpgs suggest`, and nerfstudio's `ns-eval`/`ns-viewer`.

nerfstudio reads `--load-config` with `yaml.load` and asserts the result is a `TrainerConfig`, so a truncated file
is a `yaml` parser error, and one cut between two fields loads as a config that lacks them (an `AttributeError`
later: `'HpgsPipelineConfig' object has no attribute 'model'`). `read_run_config` checks what nerfstudio would
trip on; `explain_load_config_failure` (called by the excepthook `hpgs_ns.errors` installs under nerfstudio's
CLIs) re-reads `--load-config` after `ns-eval`/`ns-viewer` failed in nerfstudio's `eval_setup`, or `ns-train
--load-config` in its `main`, and names the file's problem instead of the traceback, when it finds one. It also
names the checkpoint `eval_setup` could not load: a run folder whose nerfstudio_models holds none (an IndexError
in nerfstudio) or whose newest is truncated (torch's RuntimeError). It speaks only for the plugin's own runs (a
config.yml whose YAML tags name `hpgs_ns` classes: `names_the_plugin`); another method's run (splatfacto, ...)
keeps nerfstudio's traceback, exactly as without the plugin.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path
from typing import Optional, Sequence

from hpgs_ns.errors import UserError


class RunConfigError(UserError, ValueError):
    """A `--load-config` that is not a readable training run's config.yml."""


def read_run_config(path: Path, flag: str = "--load-config"):
    """The `TrainerConfig` in a run's config.yml (as nerfstudio loads it: `yaml.Loader`), or RunConfigError naming
    the file and the fix: a folder, a missing file, a file that is not YAML, not a run config, or is cut short."""
    import yaml
    from nerfstudio.engine.trainer import TrainerConfig

    path = Path(path)
    if path.is_dir():
        if (path / "config.yml").is_file():
            raise RunConfigError(f"{flag} {path} is a run folder; pass its config.yml: {flag} {path / 'config.yml'}")
        raise RunConfigError(f"{flag} {path} is a folder, not a run's config.yml; pass {flag} RUN/config.yml "
                             "(outputs/<experiment>/<method>/<timestamp>/config.yml)")
    if not path.is_file():
        raise RunConfigError(f"{flag} {path} not found; pass {flag} RUN/config.yml of a trained run")
    fix = "restore it, or pass the config.yml a training run wrote (outputs/<experiment>/<method>/<timestamp>/)"
    try:
        config = yaml.load(path.read_text(encoding="utf-8"), Loader=yaml.Loader)
    except Exception as err:  # yaml's parser and constructor errors, UnicodeDecodeError, a tag naming no class, ...
        detail = " ".join(str(err).split())[:120] or type(err).__name__
        raise RunConfigError(f"{path} is not a readable run config ({type(err).__name__}: {detail}); {fix}") from None
    if not isinstance(config, TrainerConfig):
        raise RunConfigError(f"{path} is not a nerfstudio run config (it holds a {type(config).__name__}); {fix}")
    missing = _missing_field(config, "config")
    if missing:
        raise RunConfigError(f"{path} is cut short or damaged (it has no {missing}); {fix}")
    return config


def _missing_field(obj, where: str, depth: int = 0) -> Optional[str]:
    """The dotted name of the first dataclass field (recursively) that `obj` has neither set nor defaults, if any.
    yaml.Loader builds objects without `__init__`, so a field cut from the file is simply absent."""
    if depth > 8 or not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        return None
    own = vars(obj)
    for f in dataclasses.fields(obj):
        if f.name not in own and not hasattr(type(obj), f.name):
            return f"{where}.{f.name}".removeprefix("config.")
        value = own.get(f.name)
        found = _missing_field(value, f"{where}.{f.name}", depth + 1)
        if found:
            return found
        if isinstance(value, dict):
            for key, item in value.items():
                for inner in (item.values() if isinstance(item, dict) else (item,)):
                    found = _missing_field(inner, f"{where}.{f.name}.{key}", depth + 1)
                    if found:
                        return found
    return None


def load_config_argument(argv: Sequence[str]) -> Optional[Path]:
    """The value of `--load-config` (either spelling, `--load-config=X` too) in a command line, if given."""
    for i, arg in enumerate(argv):
        for flag in ("--load-config", "--load_config"):
            if arg == flag and i + 1 < len(argv):
                return Path(argv[i + 1])
            if arg.startswith(flag + "="):
                return Path(arg.split("=", 1)[1])
    return None


PLUGIN_TAG = re.compile(rb"!!python/[a-z/]+:hpgs_ns\.")
"""A YAML tag naming one of the plugin's classes (`!!python/object:hpgs_ns.trainer.HpgsTrainerConfig`, the first line
of every hpgs run's config.yml, so a file cut short keeps it)."""


def names_the_plugin(path: Optional[Path]) -> bool:
    """Whether `path` (a run's config.yml, or its run folder) is a config whose YAML names the plugin's classes: the
    runs whose load failures the excepthook explains. False for a file that is missing or unreadable."""
    if path is None:
        return False
    path = Path(path)
    try:
        if path.is_dir():
            path = path / "config.yml"
        return PLUGIN_TAG.search(path.read_bytes()) is not None
    except (OSError, ValueError):
        return False


def failing_run_config(frames: Sequence, argv: Sequence[str]) -> Optional[Path]:
    """The config.yml nerfstudio was opening when it failed: `eval_setup`'s `config_path` (ns-eval, ns-viewer,
    ns-render, ...), else the command line's `--load-config` (ns-train); None when neither names one."""
    for frame in frames:
        if _in(frame, "eval_setup", "nerfstudio/utils/eval_utils.py") and frame.f_locals.get("config_path") is not None:
            return Path(frame.f_locals["config_path"])
    return load_config_argument(argv)


def _in(frame, function: str, module_file: str) -> bool:
    """Whether `frame` runs `function` of the file ending in `module_file` (e.g. "nerfstudio/scripts/train.py")."""
    return frame.f_code.co_name == function and Path(frame.f_code.co_filename).as_posix().endswith(module_file)


def explain_checkpoint_failure(frames: Sequence) -> Optional[str]:
    """The one-line message when nerfstudio's `eval_load_checkpoint` (`ns-eval`, `ns-viewer`) failed to pick or
    read the checkpoint: none in the folder, a file there that is not one, or a checkpoint that does not load."""
    at = next((k for k, f in enumerate(frames) if _in(f, "eval_load_checkpoint", "nerfstudio/utils/eval_utils.py")), None)
    if at is None:
        return None
    local = frames[at].f_locals
    folder = getattr(local.get("config"), "load_dir", None)
    if folder is None:
        return None
    folder = Path(folder)
    load_path = local.get("load_path")
    if load_path is None:  # failed choosing the newest: nerfstudio reads the step from every file name there
        others = sorted(p.name for p in folder.iterdir() if not re.fullmatch(r"step-\d+\.ckpt", p.name)) if folder.is_dir() else []
        if others:
            return (f"{folder} holds files that are not checkpoints ({', '.join(others[:3])}), and nerfstudio reads "
                    "every file there as one: move them out of it")
        return (f"{folder} holds no checkpoint (step-*.ckpt); train the run first (it saves one every --steps-per-save "
                "steps and at its last), or copy the run's nerfstudio_models there")
    callee = frames[at + 1].f_code.co_filename if at + 1 < len(frames) else ""
    if not Path(callee).as_posix().endswith("torch/serialization.py"):
        return None  # loaded, but the pipeline refused its state: not a damaged file
    from hpgs_ns.trainer import CheckpointError, checkpoint_step, load_checkpoint_file

    try:
        load_checkpoint_file(Path(load_path))
    except CheckpointError as err:
        before = sorted((p for p in folder.glob("step-*.ckpt") if checkpoint_step(p) < checkpoint_step(Path(load_path))),
                        key=checkpoint_step)
        if before:
            return f"{err}; move it out of {folder} to load the one before it ({before[-1].name})"
        return f"{err}; it is the run's only checkpoint: restore it from a copy, or train the run again"
    return None


def explain_load_config_failure(value: BaseException, traceback, argv: Sequence[str] = ()) -> Optional[str]:
    """The one-line message for an exception raised while nerfstudio's `eval_setup` (`ns-eval`, `ns-viewer`, ...)
    or `ns-train`'s `main` read `--load-config`, when re-reading that file finds what is wrong with it, or
    `eval_setup` could not load the run's checkpoint (`explain_checkpoint_failure`); None otherwise, and always
    None when the run's config.yml does not name the plugin's classes (`names_the_plugin`)."""
    frames = []
    while traceback is not None:
        frames.append(traceback.tb_frame)
        traceback = traceback.tb_next
    if isinstance(value, UserError):
        return None
    path = failing_run_config(frames, list(argv or sys.argv[1:]))
    if not names_the_plugin(path):
        return None  # not an hpgs run (or none at all): nerfstudio's own traceback, as without the plugin
    checkpoint = explain_checkpoint_failure(frames)
    if checkpoint is not None:
        return checkpoint
    reading = any(_in(f, "eval_setup", "nerfstudio/utils/eval_utils.py") or _in(f, "main", "nerfstudio/scripts/train.py")
                  for f in frames)
    if not reading:
        return None
    try:
        read_run_config(path)
    except RunConfigError as err:
        return str(err)
    except Exception:  # a broken install, not the file: keep the original traceback
        return None
    return None
