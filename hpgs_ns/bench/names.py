"""The names of the benchmark's reference rows, spelled once.

A reference row is a run beside the selectors that adds no view by choice: `initial` trains on the initial views
alone (what the added views are measured against), `all` on every training view from step 0 (a ceiling).
They are never compared with a selector, and they take no selector options. Plain strings, no imports: stats
and the early-stop fitting read them without pulling in the selectors (and torch).
"""

from __future__ import annotations

from typing import Tuple

INITIAL = "initial"
"""No view added: the initial views only, trained for the same steps."""
ALL = "all"
"""Every training view from step 0."""
REFERENCES: Tuple[str, ...] = (INITIAL, ALL)
"""Every reference row, in the order tables list them (after the selectors)."""


def is_reference(name: str) -> bool:
    return name in REFERENCES
