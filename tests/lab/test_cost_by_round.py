"""The report renders where the schedule cost lands from the lab's `cost_by_round.json`, and nothing without it."""

from __future__ import annotations

import json

from hpgs_lab.report import write_report
from hpgs_lab.report.cost_by_round import cost_by_round_section


def group(mean: float, views: int) -> dict:
    return {"mean": mean, "views": views}


def test_the_section_is_a_table_of_selectors_by_round_group(tmp_path):
    report = {"default": {
        "cost_by_group": {"initial": group(-0.3, 10), "rounds 1-8": group(0.125, 20), "rounds 13-16": group(1.0, 5)},
        "cost_by_group_by_selector": {
            "random": {"initial": group(-0.25, 6), "rounds 1-8": group(0.5, 12)},
            "farthest": {"initial": group(-0.375, 4), "rounds 1-8": group(-0.25, 8), "rounds 13-16": group(1.0, 5)}}}}
    (tmp_path / "cost_by_round.json").write_text(json.dumps(report))
    lines = cost_by_round_section(tmp_path).splitlines()
    assert "| start | selector | initial | rounds 1-8 | rounds 9-12 | rounds 13-16 |" in lines
    rows = [line for line in lines if line.startswith("| default |")]
    assert rows == ["| default | farthest | -0.38 (4) | -0.25 (8) | – | +1.00 (5) |",
                    "| default | random | -0.25 (6) | +0.50 (12) | – | – |",
                    "| default | all selectors | -0.30 (10) | +0.12 (20) | – | +1.00 (5) |"]


def test_a_folder_without_the_file_gets_no_section_and_no_stale_page(tmp_path):
    assert cost_by_round_section(tmp_path) == ""
    (tmp_path / "cost_by_round.md").write_text("stale")
    write_report(tmp_path)
    assert not (tmp_path / "cost_by_round.md").exists()
