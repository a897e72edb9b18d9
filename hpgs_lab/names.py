"""The names of the benchmark's reference rows, spelled once.

A reference row is a run beside the selectors that adds no view by choice: `initial` trains on the initial views
alone (what the added views are measured against), `all` on every training view from step 0 (a ceiling).
They are never compared with a selector, and they take no selector options. Plain strings, no imports: stats
and the early-stop fitting read them without pulling in the selectors (and torch).

`final-set` is a reference of one selector run rather than of a scene: that run's final views (initial and chosen)
trained from step 0 with its seed and steps (`hpgs bench --final-set`). Its results sit beside the run's
(`<selector>/final-set/seed<k>.json`), not among the rows, and the report sets them against their runs only
(the schedule cost, `report.schedule`).
"""

from __future__ import annotations

from typing import Tuple

INITIAL = "initial"
"""No view added: the initial views only, trained for the same steps."""
ALL = "all"
"""Every training view from step 0."""
REFERENCES: Tuple[str, ...] = (INITIAL, ALL)
"""Every reference row, in the order tables list them (after the selectors)."""
FINAL_SET = "final-set"
"""A selector run's final views, trained from step 0 with no rounds (the run's schedule cost is measured by it)."""


def is_reference(name: str) -> bool:
    """A reference row or a final-set reference: a run that no selector chose views for."""
    return name in REFERENCES or name == FINAL_SET
