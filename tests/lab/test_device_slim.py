"""scripts/device_slim.sh: around a lease the committed results leave the working tree (the preference models stay,
the GPU machine reads them) and come back unchanged."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "device_slim.sh"


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, check=True).stdout


@pytest.fixture()
def repo(tmp_path: Path) -> Path:
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    (tmp_path / "scripts").mkdir()
    shutil.copy(SCRIPT, tmp_path / "scripts" / "device_slim.sh")
    for name in ("pref_models/tune.pt", "real6/bonsai/seed0.json", "tune6/room-lab/seed1.json"):
        path = tmp_path / "benchmarks" / "results" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(name)
    (tmp_path / ".gitignore").write_text("/.dev-results/\n")
    git(tmp_path, "init", "-q")
    git(tmp_path, "add", "-A")
    git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "results")
    return tmp_path


def slim(repo: Path, verb: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "scripts/device_slim.sh", verb], cwd=repo, capture_output=True, text=True)


def test_out_leaves_only_the_preference_models_and_nothing_the_device_would_carry(repo):
    assert slim(repo, "out").returncode == 0
    assert sorted(p.name for p in (repo / "benchmarks" / "results").iterdir()) == ["pref_models"]
    carried = git(repo, "ls-files", "--others", "--exclude-standard")
    assert carried == ""  # the held results are ignored: no call carries them
    assert (repo / ".dev-results" / "real6" / "bonsai" / "seed0.json").read_text() == "real6/bonsai/seed0.json"


def test_back_restores_every_file_and_a_lost_hold_comes_back_from_git(repo):
    slim(repo, "out")
    shutil.rmtree(repo / ".dev-results" / "tune6")  # a hold that lost a folder
    done = slim(repo, "back")
    assert done.returncode == 0
    assert git(repo, "status", "--porcelain") == ""
    assert (repo / "benchmarks" / "results" / "real6" / "bonsai" / "seed0.json").read_text() == "real6/bonsai/seed0.json"
    assert (repo / "benchmarks" / "results" / "tune6" / "room-lab" / "seed1.json").is_file()
    assert not (repo / ".dev-results").exists()


def test_out_refuses_uncommitted_results_with_one_line(repo):
    (repo / "benchmarks" / "results" / "real6" / "bonsai" / "seed1.json").write_text("new")
    done = slim(repo, "out")
    assert done.returncode == 1
    assert done.stderr.strip() == ("device_slim.sh: benchmarks/results has uncommitted changes; commit them before "
                                   "moving it out")
    assert (repo / "benchmarks" / "results" / "real6").is_dir()


def test_back_keeps_a_folder_merged_during_the_lease_and_fills_in_the_rest(repo):
    slim(repo, "out")
    merged = repo / "benchmarks" / "results" / "real6" / "fox" / "seed0.json"  # merged before `back`
    merged.parent.mkdir(parents=True)
    merged.write_text("new run")
    done = slim(repo, "back")
    assert done.returncode == 0
    assert merged.read_text() == "new run"
    assert (repo / "benchmarks" / "results" / "real6" / "bonsai" / "seed0.json").read_text() == "real6/bonsai/seed0.json"
    assert git(repo, "status", "--porcelain") == "?? benchmarks/results/real6/fox/\n"
    assert not (repo / ".dev-results").exists()


def test_out_refuses_a_hold_left_from_an_earlier_lease_and_moves_nothing(repo):
    (repo / ".dev-results" / "real6").mkdir(parents=True)
    done = slim(repo, "out")
    assert done.returncode == 1
    assert done.stderr.strip() == ("device_slim.sh: .dev-results/real6 is left from an earlier lease; run "
                                   "'bash scripts/device_slim.sh back' first")
    assert (repo / "benchmarks" / "results" / "tune6" / "room-lab" / "seed1.json").is_file()
