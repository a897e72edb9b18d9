"""benchmarks/done_when_46.py: #46's bar on the schedule cost, and the run PSNR of a mechanism against its base."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import load_script, make_result, write_rows

from hpgs_lab.results import SourceRun, load_final_sets

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "done_when_46.py"
SCENES = ("s1", "s2", "s3")
VIEWS = {"initial_views": ["v0"], "chosen_views": ["v1"], "num_views_final": 2}


@pytest.fixture(scope="module")
def done_when():
    return load_script(SCRIPT)


def folder(root: Path, cost: dict, run_psnr: float = 20.0, wall: float = 100.0, scenes=SCENES) -> Path:
    """FisherRF runs of each selector (seeds 0-1) at `run_psnr` (+0.1 on seed 1) with final-sets `cost[selector]` dB
    above them, and one HP-GS-protocol run that must not count."""
    for scene in scenes:
        for selector, c in cost.items():
            for seed in (0, 1):
                psnr = run_psnr + 0.1 * seed
                write_rows(root, [make_result(scene, "fisherrf", selector, seed, psnr, wall=wall, **VIEWS)])
                make_result(scene, "fisherrf", "final-set", seed, psnr + c, wall=wall, **VIEWS,
                            final_set_of=SourceRun(selector, seed, 0, ["v0", "v1"])).to_json(
                    root / scene / "fisherrf" / selector / "final-set" / f"seed{seed}.json")
    write_rows(root, [make_result(scenes[0], "hpgs", "hpgs", 0, 5.0, **VIEWS)])
    return root


def test_the_bar_holds_only_when_the_pooled_mean_its_upper_end_and_every_selector_are_under_it(done_when, tmp_path):
    low = folder(tmp_path / "low", {"random": 0.1, "farthest": 0.2, "fisher": 0.3, "hpgs": 0.2})
    out = done_when.done_when(done_when.runs_of(low), load_final_sets(low))
    assert out["all selectors"]["mean"] == pytest.approx(0.2) and out["all selectors"]["pairs"] == 24
    assert out["selectors"]["fisher"]["mean"] == pytest.approx(0.3) and out["met"]
    # one selector above +0.5 fails the bar though the pooled mean (0.275) is under 0.3
    one_high = folder(tmp_path / "one", {"random": 0.0, "farthest": 0.0, "fisher": 0.0, "hpgs": 0.6})
    out = done_when.done_when(done_when.runs_of(one_high), load_final_sets(one_high))
    assert out["all selectors"]["mean"] == pytest.approx(0.15) and not out["met"]


def test_run_gain_pairs_only_runs_that_differ_from_the_base(done_when, tmp_path):
    cost = {"random": 0.1, "hpgs": 0.2}
    base = done_when.runs_of(folder(tmp_path / "base", cost, run_psnr=20.0, wall=100.0))
    arm = folder(tmp_path / "arm", cost, run_psnr=19.7, wall=105.0, scenes=SCENES[:2])
    folder(tmp_path / "arm", cost, run_psnr=20.0, wall=100.0, scenes=SCENES[2:])  # s3 copied from the base
    vs = done_when.against(done_when.runs_of(arm), base, min_gain=-0.2)
    assert vs["run_gain"]["pairs"] == 8 and vs["run_gain"]["scenes"] == 2
    assert vs["run_gain"]["mean"] == pytest.approx(-0.3) and not vs["run_gain_met"]
    assert vs["wall_ratio"] == pytest.approx(1.05)
    assert done_when.against(done_when.runs_of(arm), base, min_gain=-0.4)["run_gain_met"]


def test_run_gain_over_a_subset_of_scenes(done_when, tmp_path):
    cost = {"random": 0.1}
    base = done_when.runs_of(folder(tmp_path / "base", cost, run_psnr=20.0))
    folder(tmp_path / "arm", cost, run_psnr=19.5, scenes=SCENES[:1])  # s1 loses 0.5 dB, s2 and s3 gain 0.4
    arm = done_when.runs_of(folder(tmp_path / "arm", cost, run_psnr=20.4, scenes=SCENES[1:]))
    every = done_when.against(arm, base, min_gain=-0.1)["run_gain"]
    assert every["mean"] == pytest.approx((-0.5 + 0.4 + 0.4) / 3) and every["pairs"] == 6
    sub = done_when.against(arm, base, min_gain=-0.1, scenes=["s2", "s3"])["run_gain"]
    assert sub["mean"] == pytest.approx(0.4) and sub["pairs"] == 4 and sub["scenes"] == 2
    assert sub["p"] == pytest.approx(0.5)  # two scenes, both positive: the sign-flip floor 2 / 2^2


def test_run_and_final_set_gains_per_selector(done_when, tmp_path):
    base_dir = folder(tmp_path / "base", {"random": 0.1, "hpgs": 0.2}, run_psnr=20.0)
    arm_dir = folder(tmp_path / "arm", {"random": 0.3, "hpgs": 0.9}, run_psnr=19.8)
    per = done_when.selector_gains(done_when.runs_of(arm_dir), done_when.runs_of(base_dir), load_final_sets(arm_dir),
                                   load_final_sets(base_dir))
    assert set(per) == {"random", "hpgs"}
    assert per["random"]["run"]["mean"] == pytest.approx(-0.2) and per["random"]["run"]["pairs"] == 6
    # final-sets: (19.8 + 0.3) - (20.0 + 0.1) for random, (19.8 + 0.9) - (20.0 + 0.2) for hpgs
    assert per["random"]["final_set"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert per["hpgs"]["final_set"]["mean"] == pytest.approx(0.5) and per["hpgs"]["final_set"]["pairs"] == 6
