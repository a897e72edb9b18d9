"""The base class of every failure a user can fix, and how nerfstudio's CLIs print it: one line, no traceback.

`ns-train hpgs`, `ns-eval` and `ns-viewer` are nerfstudio's entry points, so this package cannot wrap their
`main`; `install_excepthook` (run when nerfstudio loads the `hpgs` method, in every `ns-*` process: it lists all
methods) prints an uncaught `UserError` as `error: <message>` and exits 1, and so is another package's exception that
a registered explainer names the cause of (a damaged `--load-config` or checkpoint of an hpgs run:
`hpgs_ns.run_config`). Any other exception goes, untouched, to the hook installed before (nerfstudio's or Python's):
it prints exactly as without the plugin. HPGS_TRACEBACK=1 shows the traceback for all.
"""

from __future__ import annotations

import os
import sys
from typing import Any, Callable, List, Optional


class UserError(Exception):
    """A failure the user can fix; the message is one line naming the thing and the fix."""


class OptionError(UserError):
    """An option's value makes no sense; raised by configs' `__post_init__`, which tyro runs while it parses the
    command line (before nerfstudio prints the config or makes a run folder). Not a ValueError: tyro would catch that
    and draw its own error box."""


def check_option(flag: str, value: object, ok: bool, need: str, fix: str = "") -> None:
    """Raise `OptionError` "FLAG VALUE: NEED[; FIX]" unless `ok`; a sequence value is written as its words."""
    if ok:
        return
    shown = " ".join(map(str, value)) if isinstance(value, (tuple, list)) else str(value)
    raise OptionError(f"{flag} {shown or '(empty)'}: {need}" + (f"; {fix}" if fix else ""))


def print_user_errors(kind, value, traceback, fallback) -> None:
    if os.environ.get("HPGS_TRACEBACK"):
        fallback(kind, value, traceback)
        return
    if issubclass(kind, UserError):
        print(f"error: {value}", file=sys.stderr)
        return
    if issubclass(kind, Exception):
        for explain in EXPLAINERS:  # e.g. ns-eval / ns-viewer failing in nerfstudio on an hpgs run's damaged config.yml
            try:
                message = explain(value, traceback)
            except Exception:  # an explainer's own failure must not change what the exception prints
                message = None
            if message:
                print(f"error: {message}", file=sys.stderr)
                return
    fallback(kind, value, traceback)


EXPLAINERS: List[Callable[[BaseException, Any], Optional[str]]] = []
"""Functions that name, in one line, the fixable cause of an exception raised in another package's code (None when
they find none): `hpgs_ns.run_config.explain_load_config_failure`, registered by `install_excepthook`'s caller. An
explainer names only failures of the plugin's own runs; one that raises counts as None."""


def install_excepthook(explain: Optional[Callable[[BaseException, Any], Optional[str]]] = None) -> None:
    """Idempotent; chains to the hook installed before (nerfstudio's or Python's). `explain`: added to
    `EXPLAINERS` (once)."""
    if explain is not None and explain not in EXPLAINERS:
        EXPLAINERS.append(explain)
    if getattr(sys.excepthook, "hpgs_user_errors", False):
        return
    previous = sys.excepthook

    def hook(kind, value, traceback):
        print_user_errors(kind, value, traceback, previous)

    hook.hpgs_user_errors = True  # type: ignore[attr-defined]
    sys.excepthook = hook
