"""scripts/merge_pilot_results.py: a device pilot's results into a results folder, never over other results."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "merge_pilot_results.py"


def merge(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, cwd=REPO)


def put(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_seed_results_of_every_sweep_land_at_their_relative_paths(tmp_path):
    s0, s1, into = tmp_path / "s0" / "reset", tmp_path / "s1" / "reset", tmp_path / "results" / "reset"
    put(s0 / "alexander/fisherrf/random/seed0.json", "r0")
    put(s0 / "alexander/fisherrf/random/final-set/seed0.json", "f0")
    put(s0 / "_runs/alexander/fisherrf/random/seed0.json", "working copy")
    put(s0 / "table.md", "report")
    put(s1 / "alexander/fisherrf/random/seed1.json", "r1")
    put(into / "alexander/fisherrf/random/seed0.json", "r0")  # already there, same content: fine

    out = merge(s0, s1, "--into", into)

    assert out.returncode == 0, out.stderr
    assert "2 result(s) copied" in out.stdout
    assert (into / "alexander/fisherrf/random/final-set/seed0.json").read_text() == "f0"
    assert (into / "alexander/fisherrf/random/seed1.json").read_text() == "r1"
    assert not (into / "_runs").exists() and not (into / "table.md").exists()


def test_a_result_with_other_content_stops_the_merge_before_any_copy(tmp_path):
    src, into = tmp_path / "s0" / "reset", tmp_path / "results"
    put(src / "a/fisherrf/hpgs/seed0.json", "new")
    put(src / "a/fisherrf/hpgs/seed1.json", "new")
    put(into / "a/fisherrf/hpgs/seed0.json", "first run")

    out = merge(src, "--into", into)

    assert out.returncode == 1
    assert "1 result(s) already in" in out.stderr and "seed0.json" in out.stderr
    assert (into / "a/fisherrf/hpgs/seed0.json").read_text() == "first run"
    assert not (into / "a/fisherrf/hpgs/seed1.json").exists()


def test_a_missing_source_is_named(tmp_path):
    out = merge(tmp_path / "nope", "--into", tmp_path / "results")
    assert out.returncode == 2 and "no such folder" in out.stderr and "nope" in out.stderr
