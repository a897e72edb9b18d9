"""docs/results.md is what `hpgs bench --report-only` makes of the committed twelve-scene matrix (issue #47), the
folder's own report pages match it, and the README's verdict lines quote it."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from hpgs_lab.report import write_report

REPO = Path(__file__).resolve().parents[2]
REAL12 = Path("benchmarks/results/real12")


def test_the_results_page_regenerates_exactly_from_the_committed_runs(tmp_path, monkeypatch):
    shutil.copytree(REPO / REAL12, tmp_path / REAL12, ignore=shutil.ignore_patterns("*.png", "*.jpg", "_*", "*.md"))
    monkeypatch.chdir(tmp_path)  # the page names the folder as the command was given it
    write_report(REAL12, results_page=tmp_path / "docs" / "results.md")
    page = (tmp_path / "docs" / "results.md").read_text()
    assert page == (REPO / "docs" / "results.md").read_text(), (
        "docs/results.md is stale: hpgs bench --out benchmarks/results/real12 --report-only --results-page docs/results.md")
    assert "## Runs not in the folder\n\nNone:" in page  # the matrix is whole
    assert "](../benchmarks/results/real12/fisherrf-paired-gains.png)" in page  # the figure, linked from docs/
    for name in sorted(p.name for p in (REPO / REAL12).glob("*.md") if p.name != "README.md"):
        assert (REAL12 / name).read_text() == (REPO / REAL12 / name).read_text(), (
            f"{REAL12 / name} is stale: hpgs bench --out {REAL12} --report-only")


def test_every_interval_in_the_readme_verdict_is_on_the_results_page():
    readme = (REPO / "README.md").read_text()
    verdict = readme[readme.index("Which one to use, from the twelve-scene matrix"):readme.index("So `ns-train hpgs` picks")]
    page = (REPO / "docs" / "results.md").read_text()
    number = r"([+\-−]\d+\.\d+)"
    quoted = re.findall(number + r"(?: dB)? \[" + number + ", " + number + r"\]", verdict)
    assert len(quoted) >= 8
    for gain, lo, hi in quoted:
        gain, lo, hi = (x.replace("−", "-") for x in (gain, lo, hi))
        assert f"| {gain} | [{lo}, {hi}] |" in page, f"README quotes {gain} [{lo}, {hi}], not on docs/results.md"
