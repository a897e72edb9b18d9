"""A training run's `config.yml`, read with one-line errors: `hpgs suggest`, and nerfstudio's `ns-eval`/`ns-viewer`.

nerfstudio reads `--load-config` with `yaml.load` and asserts the result is a `TrainerConfig`, so a truncated file
is a `yaml` parser error, and one cut between two fields loads as a config that lacks them (an `AttributeError`
later: `'HpgsPipelineConfig' object has no attribute 'model'`). `read_run_config` checks what nerfstudio would
trip on; `explain_load_config_failure` (called by the excepthook `hpgs_ns.errors` installs under nerfstudio's
CLIs) re-reads `--load-config` after `ns-eval`/`ns-viewer` failed in nerfstudio's `eval_setup`, and names the
file's problem instead of the traceback, when it finds one.
"""

from __future__ import annotations

import dataclasses
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


def explain_load_config_failure(value: BaseException, traceback, argv: Sequence[str] = ()) -> Optional[str]:
    """The one-line message for an exception raised while nerfstudio's `eval_setup` read `--load-config`
    (`ns-eval`, `ns-viewer`, ...), when re-reading that file finds what is wrong with it; None otherwise."""
    names = set()
    while traceback is not None:
        names.add(traceback.tb_frame.f_code.co_name)
        traceback = traceback.tb_next
    if "eval_setup" not in names or isinstance(value, UserError):
        return None
    path = load_config_argument(list(argv or sys.argv[1:]))
    if path is None:
        return None
    try:
        read_run_config(path)
    except RunConfigError as err:
        return str(err)
    except Exception:  # a broken install, not the file: keep the original traceback
        return None
    return None
