"""benchmarks/judge_table.py: #33's Done-when figures pool a start mode's farthest and random runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture()
def judge_table():
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import judge_table
        yield judge_table
    finally:
        sys.path.remove(str(REPO / "benchmarks"))


def write_run(root: Path, scene: str, start: str, variant: str, seed: int, psnr: float, views=("a", "b")) -> None:
    path = root / scene / start / variant / f"seed{seed}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"seed": seed, "test": {"psnr": psnr}, "initial_views": list(views), "chosen_views": [],
                                "provenance": {"settings": {"extra_args": ""}}}))


def test_done_when_pools_farthest_and_random_runs_per_start_mode(tmp_path, judge_table):
    # schedule costs (final-set - run): bonsai farthest 1.0, random 0.0; fox farthest 2.0, random 1.0; juicebox 0.3
    for scene, run, final in (("bonsai", 20.0, 21.0), ("fox", 24.0, 26.0), ("juicebox", 30.0, 30.3)):
        write_run(tmp_path, scene, "colmap", "farthest", 0, run)
        write_run(tmp_path, scene, "colmap", "final-set", 0, final)
    for scene, run, final in (("bonsai", 19.0, 19.0), ("fox", 23.0, 24.0)):
        write_run(tmp_path, scene, "colmap-random", "random", 0, run, views=("c", "d"))
        write_run(tmp_path, scene, "colmap-random", "final-set", 0, final, views=("c", "d"))
        write_run(tmp_path, scene, "active-random", "random", 0, run + 0.5, views=("c", "d"))

    # an after-add arm of the random runs, same views: it borrows colmap-random's final-set, never farthest's
    write_run(tmp_path, "bonsai", "colmap-r20-random", "random", 0, 18.5, views=("c", "d"))

    runs, setup = judge_table.load(tmp_path)
    summary = judge_table.summarise(runs, setup)
    colmap = summary["modes"]["colmap"]
    assert colmap["starts"] == ["colmap", "colmap-random"]
    assert colmap["pairs"] == 5
    # mean over scenes of per-scene means: (0.5 + 1.5 + 0.3) / 3
    assert colmap["cost_mean"] == pytest.approx((0.5 + 1.5 + 0.3) / 3)
    assert colmap["cost_lo"] <= colmap["cost_mean"] <= colmap["cost_hi"]
    # fox's bar counts every 20-view run of the mode: random's 23.0 misses 23.5 although farthest's 24.0 meets it
    assert colmap["fox"] == {"colmap:0": 24.0, "colmap-random:0": 23.0}
    assert colmap["fox_pass"] is False
    # the farthest-only figures of the `colmap` start are untouched by the random runs
    assert summary["starts"]["colmap"]["cost_mean"] == pytest.approx((1.0 + 2.0 + 0.3) / 3)
    [arm] = [r for r in summary["table"] if r["start"] == "colmap-r20-random"]
    assert arm["final_set_of"] == "colmap-random" and arm["cost"] == {0: pytest.approx(0.5)}
    # random arms pair with random arms, by scene and seed
    gains = judge_table.arm_gains(runs, "active-random", "colmap-random")
    assert gains == {"bonsai": {0: pytest.approx(0.5)}, "fox": {0: pytest.approx(0.5)}}


def test_a_bench_folder_is_filed_per_start_and_selector_and_read_by_the_judge(tmp_path, judge_table):
    import file_judge_runs

    bench = tmp_path / "bench"  # `hpgs bench --out` layout
    for selector, run, final in (("farthest", 20.0, 21.0), ("random", 19.0, 19.5), ("fisher", 22.0, 22.0)):
        d = bench / "stitch" / "fisherrf" / selector
        (d / "final-set").mkdir(parents=True)
        (d / "seed0.json").write_text(json.dumps({"seed": 0, "test": {"psnr": run}, "initial_views": ["a"],
                                                  "chosen_views": [], "worst_views": [{"image": "w.jpg"}]}))
        (d / "w.jpg").write_bytes(b"jpeg")
        (d / "final-set" / "seed0.json").write_text(json.dumps({"seed": 0, "test": {"psnr": final}}))
    root = tmp_path / "judge"
    written = file_judge_runs.file_runs(bench, "active", root)
    assert sorted(p.relative_to(root).as_posix() for p in written) == [
        "stitch/active-random/final-set/seed0.json", "stitch/active-random/random/seed0.json",
        "stitch/active/farthest/seed0.json", "stitch/active/final-set/seed0.json"]  # fisher is not the judge's
    assert (root / "stitch" / "active" / "farthest" / "w.jpg").read_bytes() == b"jpeg"
    runs, _ = judge_table.load(root)
    assert runs[("stitch", "active", "final-set")][0]["psnr"] == 21.0
    assert runs[("stitch", "active-random", "final-set")][0]["psnr"] == 19.5
