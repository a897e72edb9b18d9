"""`RunResult`: every layout of the committed results reads with the values it holds (defaults where it predates
a key), the current version round-trips, and what cannot be read is a one-line error."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import make_result

from hpgs_lab.results import (
    VERSION,
    ResultError,
    RoundPsnr,
    RunResult,
    ViewMetrics,
    load_results,
)

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


# --- version 1: the flat files written before RunResult, in the five layouts committed ----------------------


def test_the_oldest_layout_gets_the_defaults_of_every_later_key():
    r = RunResult.from_json(RESULTS / "stress/occluded+exposure/hpgs/random/seed0.json")
    assert (r.scene, r.protocol, r.selector, r.seed, r.steps) == ("occluded+exposure", "hpgs", "random", 0, 225)
    assert r.test.psnr == 18.23024559020996 and r.test.lpips == 0.3187446892261505
    assert (r.num_test_views, r.num_views_final) == (6, 13)
    assert r.psnr_per_round[0] == RoundPsnr(30, 6, 16.714083671569824)
    assert r.initial_views == ["0001.png", "0010.png", "0019.png", "0029.png", "0038.png", "0047.png"]
    assert r.timing.wall_seconds == 65.84312753099948 and r.timing.peak_host_rss_mb == 1187.5546875
    assert r.timing.peak_gpu_allocated_mb is None
    assert r.provenance.device == "cpu x2"
    # keys this layout predates
    assert (r.repeat, r.smoke, r.num_train_views, r.selection_work, r.psnr_at_round_steps) == (0, False, None, {}, {})
    assert (r.timing.sweep_id, r.timing.started_at, r.timing.runs_per_gpu) == (None, None, 1)
    assert (r.provenance.settings, r.provenance.git_commit, r.provenance.libraries) == (None, None, {})
    assert r.test_views == [] and r.dataparser is None
    # the scene folder, recovered from the recorded command
    assert r.data == "/work/stress-bench/out/_scenes/occluded+exposure"


def test_a_layout_with_selection_work_but_no_settings():
    r = RunResult.from_json(RESULTS / "bench/bonsai/hpgs/hpgs/seed2.json")
    assert r.selection_work == {"views_rendered": 1540.0, "pixels_rendered": 116251520.0,
                                "pixels_full_resolution": 162831900.0, "model_forwards": 1540.0}
    assert r.provenance.settings is None and r.provenance.device == "NVIDIA H100 80GB HBM3"
    assert r.data == "/work/main/.dev/bonsai" and r.timing.peak_gpu_allocated_mb == 1617.74267578125


def test_a_layout_with_the_first_settings():
    r = RunResult.from_json(RESULTS / "stress-pose-refinement/occluded+pose-noise/hpgs/hpgs/seed0.json")
    assert r.provenance.settings["steps"] == 225 and r.provenance.settings["downscale_factor"] is None
    assert r.dataparser is None  # those settings did not name it
    assert r.timing.selection_seconds == 13.281054487983056 and len(r.timing.selection_seconds_per_round) == 7


def test_a_layout_with_provenance_and_sweep_timing():
    r = RunResult.from_json(RESULTS / "suite/bonsai/fisherrf/hpgs/seed1.json")
    assert (r.repeat, r.smoke, r.num_train_views, r.num_views_final) == (0, False, 220, 20)
    assert r.provenance.git_commit == "7fd77cdb05ed906a61ec200fc2d17f17ec00dea8+dirty"
    assert r.provenance.libraries == {"hpgs_ns": "0.2.0", "torch": "2.11.0", "gsplat": "1.4.0", "nerfstudio": "1.1.5"}
    assert (r.timing.sweep_id, r.timing.runs_per_gpu, r.timing.started_at) == ("vm-1795556602", 4, 1795556602.910999)
    assert r.dataparser == "mipnerf360" and r.data == "/work/main/.devdata/mipnerf360-bonsai-device"
    assert r.psnr_at_round_steps == {}  # before eval-each-round


def test_the_newest_flat_layout_has_the_psnr_at_every_round_step():
    r = RunResult.from_json(RESULTS / "suite/juicebox/hpgs/farthest/seed3.json")
    assert r.psnr_at_round_steps[2000] == 17.64054524898529 and sorted(r.psnr_at_round_steps)[-1] == 14000
    assert r.provenance.settings["code"] == "63c8de939ec59577" and r.timing.sweep_id == "vm-1795614365.2993"
    assert r.chosen_views[:2] == ["images/0039.jpg", "images/0009.jpg"] and r.num_test_views == 8
    assert r.data == "/tmp/devdata/juicebox" and not r.is_reference


def test_every_committed_result_reads():
    for folder in ("suite", "bench", "stress", "stress-pose-refinement"):
        rows = load_results(RESULTS / folder)
        assert rows and all(r.data for r in rows)
    assert len(load_results(RESULTS / "suite")) == 120


# --- the current version -------------------------------------------------------------------------------------


def test_the_current_version_round_trips_with_its_version(tmp_path):
    r = make_result("ring", "fisherrf", "fisher", 2, 21.5, 0.61, 0.27, wall=12.0, selection=1.5, sweep_id="vm-1.2",
                    started_at=100.0, settings={"code": "abc"}, repeat=1, steps=300, data="/scenes/ring",
                    dataparser="mipnerf360", initial_views=["a.png"], chosen_views=["c.png", "b.png"],
                    psnr_per_round=[RoundPsnr(100, 1, 19.0), RoundPsnr(200, 2, None)],
                    psnr_at_round_steps={100: 19.0, 200: 20.0}, selection_work={"views_rendered": 4.0},
                    test_views=[ViewMetrics("images/t0.png", 22.0, 0.7, 0.2)])
    path = r.to_json(tmp_path / "seed2-repeat1.json")
    data = json.loads(path.read_text())
    assert data["version"] == VERSION == 2
    assert data["psnr_at_round_steps"] == {"100": 19.0, "200": 20.0}  # JSON keys are strings
    assert data["test_views"] == [{"name": "images/t0.png", "psnr": 22.0, "ssim": 0.7, "lpips": 0.2}]
    assert data["timing"]["sweep_id"] == "vm-1.2" and data["provenance"]["settings"] == {"code": "abc"}
    assert RunResult.from_json(path) == r
    assert [p.name for p in tmp_path.iterdir()] == ["seed2-repeat1.json"]  # no temp file left


def test_an_old_result_rewritten_is_the_same_run(tmp_path):
    old = RunResult.from_json(RESULTS / "suite/juicebox/hpgs/farthest/seed3.json")
    assert RunResult.from_json(old.to_json(tmp_path / "seed3.json")) == old


def test_unreadable_results_are_one_line_errors(tmp_path):
    path = tmp_path / "seed0.json"
    path.write_text(json.dumps({"version": 3}))
    with pytest.raises(ResultError, match=r"seed0.json: result version 3 is newer than this hpgs_ns reads \(2\); upgrade"):
        RunResult.from_json(path)
    path.write_text(json.dumps({"scene": "s"}))
    with pytest.raises(ResultError, match=r"seed0.json: not a benchmark result \(KeyError: 'protocol'\); re-run it"):
        RunResult.from_json(path)
    path.write_text("{")
    with pytest.raises(ResultError, match="seed0.json is not readable JSON .*; re-run it or move it out"):
        RunResult.from_json(path)
