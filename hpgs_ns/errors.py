"""The base class of every failure a user can fix, and how nerfstudio's CLIs print it: one line, no traceback.

`ns-train hpgs`, `ns-eval` and `ns-viewer` are nerfstudio's entry points, so this package cannot wrap their
`main`; `install_excepthook` (run when nerfstudio loads the `hpgs` method) prints an uncaught `UserError` as
`error: <message>` and exits 1. Any other exception keeps its traceback. HPGS_TRACEBACK=1 shows it for all.
"""

from __future__ import annotations

import os
import sys


class UserError(Exception):
    """A failure the user can fix; the message is one line naming the thing and the fix."""


def print_user_errors(kind, value, traceback, fallback) -> None:
    if issubclass(kind, UserError) and not os.environ.get("HPGS_TRACEBACK"):
        print(f"error: {value}", file=sys.stderr)
        return
    fallback(kind, value, traceback)


def install_excepthook() -> None:
    """Idempotent; chains to the hook installed before (nerfstudio's or Python's)."""
    if getattr(sys.excepthook, "hpgs_user_errors", False):
        return
    previous = sys.excepthook

    def hook(kind, value, traceback):
        print_user_errors(kind, value, traceback, previous)

    hook.hpgs_user_errors = True  # type: ignore[attr-defined]
    sys.excepthook = hook
