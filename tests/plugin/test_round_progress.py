"""A selection round that renders views shows a progress bar of them; one that renders none shows nothing."""

from __future__ import annotations

import dataclasses
import io

from rich.console import Console
from test_coverage import ACTIVE, context, ring

from hpgs_ns.selection import rounds
from hpgs_ns.selectors.coverage import CoverageSelectorConfig
from hpgs_ns.selectors.farthest import FarthestSelectorConfig


def test_the_bar_counts_the_views_a_selector_reports_and_only_once_it_reports(monkeypatch):
    screen = io.StringIO()
    monkeypatch.setattr(rounds, "CONSOLE", Console(file=screen, force_terminal=True, width=100))
    with rounds.RoundProgress("selection round 1 (farthest)", 30) as idle:
        pass
    assert idle.bar is None and screen.getvalue() == ""  # farthest renders nothing: no bar
    with rounds.RoundProgress("selection round 2 (coverage)", 30) as progress:
        progress.advance(8)
        progress.advance(4)
        assert progress.bar.tasks[0].completed == 12 and progress.bar.tasks[0].total == 30
    assert "selection round 2 (coverage)" in screen.getvalue()


def test_a_rendering_selector_reports_every_view_it_renders_and_farthest_none():
    cameras = ring()
    candidates = [i for i in range(24) if i not in ACTIVE]
    seen = []
    ctx = dataclasses.replace(context(cameras, ACTIVE, candidates), progress=seen.append)
    selection = CoverageSelectorConfig().setup().select(ctx)
    assert sum(seen) == selection.work["views_rendered"] == len(ACTIVE) + len(candidates)
    seen.clear()
    FarthestSelectorConfig().setup().select(ctx)
    assert seen == []
