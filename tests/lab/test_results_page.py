"""docs/results.md is what `hpgs bench --report-only` makes of the committed runs, and the README's verdict lines
quote it."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from hpgs_lab.report import write_report

REPO = Path(__file__).resolve().parents[2]
SUITE = Path("benchmarks/results/suite")


def test_the_results_page_regenerates_exactly_from_the_committed_runs(tmp_path, monkeypatch):
    shutil.copytree(REPO / SUITE, tmp_path / SUITE, ignore=shutil.ignore_patterns("*.png", "*.jpg", "_*"))
    monkeypatch.chdir(tmp_path)  # the page names the folder as the command was given it
    write_report(SUITE, results_page=tmp_path / "results.md")
    assert (tmp_path / "results.md").read_text() == (REPO / "docs" / "results.md").read_text(), (
        "docs/results.md is stale: hpgs bench --out benchmarks/results/suite --report-only --results-page docs/results.md")


def test_every_interval_in_the_readme_verdict_is_on_the_results_page():
    readme = (REPO / "README.md").read_text()
    verdict = readme[readme.index("Which one to use, from the six-scene suite"):readme.index("So if you pick one")]
    page = (REPO / "docs" / "results.md").read_text()
    number = r"([+\-−]\d+\.\d+)"
    quoted = re.findall(number + r"(?: dB)? \[" + number + ", " + number + r"\]", verdict)
    assert len(quoted) >= 8
    for gain, lo, hi in quoted:
        gain, lo, hi = (x.replace("−", "-") for x in (gain, lo, hi))
        assert f"| {gain} | [{lo}, {hi}] |" in page, f"README quotes {gain} [{lo}, {hi}], not on docs/results.md"


def test_the_real12_report_regenerates_exactly_from_its_committed_runs(tmp_path, monkeypatch):
    # issue #47's matrix: every wave merged into benchmarks/results/real12 must leave its report current
    real12 = Path("benchmarks/results/real12")
    shutil.copytree(REPO / real12, tmp_path / real12, ignore=shutil.ignore_patterns("*.png", "*.jpg", "_*", "*.md"))
    monkeypatch.chdir(tmp_path)
    write_report(real12)
    pages = sorted(p.name for p in (REPO / real12).glob("*.md") if p.name != "README.md")
    assert {"table.md", "paired.md", "hpgs_paper.md"} <= set(pages)
    for name in pages:
        assert (real12 / name).read_text() == (REPO / real12 / name).read_text(), (
            f"{real12 / name} is stale: hpgs bench --out {real12} --report-only")
