"""benchmarks/done_when_46.py: #46's bar on the schedule cost, and the run PSNR of a mechanism against its base."""

from __future__ import annotations

import dataclasses
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


def test_cost_difference_pairs_each_run_with_its_base_run(done_when, tmp_path):
    base_dir = folder(tmp_path / "base", {"random": 0.5, "hpgs": 0.3}, run_psnr=20.0)
    arm_dir = folder(tmp_path / "arm", {"random": 0.2, "hpgs": 0.4}, run_psnr=19.0, scenes=SCENES[:2])
    diff = done_when.cost_difference(done_when.runs_of(arm_dir), done_when.runs_of(base_dir),
                                     load_final_sets(arm_dir), load_final_sets(base_dir))
    # per scene: random -0.3, hpgs +0.1 (two seeds each), the run PSNR itself does not enter
    assert diff["mean"] == pytest.approx(-0.1) and diff["pairs"] == 8 and diff["scenes"] == 2
    assert done_when.cost_difference(done_when.runs_of(arm_dir), [], load_final_sets(arm_dir), []) is None


def test_final_sets_on_the_same_views_read_as_replicates_and_set_one_reference_for_both_costs(done_when, tmp_path):
    from hpgs_lab.results import ViewMetrics

    def final_set(psnr, views, view_psnr, seed=0, selector="random"):
        return make_result("s1", "fisherrf", "final-set", seed, psnr, **VIEWS, final_set_of=SourceRun(
            selector, seed, 0, views), test_views=[ViewMetrics(n, p, 0.5, 0.3) for n, p in view_psnr.items()])

    base = [final_set(20.0, ["v0", "v1"], {"t0": 20.0, "t8": 20.0}),
            final_set(21.0, ["v0", "v2"], {"t0": 21.0, "t8": 21.0}, seed=1),
            final_set(22.0, ["v0", "v3"], {"t0": 22.0, "t8": 22.0}, selector="hpgs")]
    arm = [final_set(19.0, ["v1", "v0"], {"t0": 24.0, "t8": 14.0}),  # same views, listed in another order
           final_set(21.5, ["v0", "v2"], {"t0": 21.5, "t8": 21.5}, seed=1),
           final_set(23.0, ["v0", "v4"], {"t0": 23.0, "t8": 23.0}, selector="hpgs")]  # other views: no replicate
    reps = done_when.replicate_final_sets(arm, base)
    assert set(reps) == {"random"} and reps["random"]["pairs"] == 2
    assert reps["random"]["mean"] == pytest.approx(-0.25)  # (-1.0 + 0.5) / 2
    assert reps["random"]["sd"] == pytest.approx(1.5 / 2 ** 0.5)
    assert reps["random"]["worst_view_gap"] == pytest.approx(-6.0) and reps["random"]["worst_view"] == "s1 seed0 t8"
    # with the renders' depths recorded, the line says how near each copy's opaque pixels reach
    arm[0] = final_set(19.0, ["v0", "v1"], {"t0": 24.0, "t8": 14.0})
    arm[0].test_views[1] = ViewMetrics("t8", 14.0, 0.5, 0.3, depth_p10=0.02, depth_median=1.5)
    base[0].test_views[1] = ViewMetrics("t8", 20.0, 0.5, 0.3, depth_p10=0.9, depth_median=1.6)
    assert done_when.replicate_final_sets(arm, base)["random"]["worst_view"] == "s1 seed0 t8; depth p10 0.02 here, 0.9 there"
    runs = [make_result("s1", "fisherrf", "random", 0, 19.0), make_result("s1", "fisherrf", "random", 1, 20.0)]
    base_runs = [make_result("s1", "fisherrf", "random", 0, 19.5), make_result("s1", "fisherrf", "random", 1, 20.0)]
    both = done_when.cost_against_both(runs, base_runs, arm, base, reps["random"]["keys"])
    # references: seed 0 (19 + 20) / 2 = 19.5, seed 1 (21.5 + 21) / 2 = 21.25
    assert both["pairs"] == 2
    assert both["folder"] == pytest.approx(((19.5 - 19.0) + (21.25 - 20.0)) / 2)
    assert both["base"] == pytest.approx(((19.5 - 19.5) + (21.25 - 20.0)) / 2)


def test_near_views_count_the_run_views_nearer_than_their_final_sets_and_what_they_cost(done_when):
    from hpgs_lab.results import ViewMetrics

    def pair(seed, run_views, final_views, start):
        views = lambda vs: [ViewMetrics(f"t{i}", p, 0.5, 0.3, depth_p10=d, depth_median=2 * d)  # noqa: E731
                            for i, (p, d) in enumerate(vs)]
        run = make_result("s1", "fisherrf", "random", seed, sum(p for p, _ in run_views) / len(run_views), **VIEWS,
                          test_views=views(run_views), seed_points=start)
        final = make_result("s1", "fisherrf", "final-set", seed, sum(p for p, _ in final_views) / len(final_views),
                            **VIEWS, test_views=views(final_views), final_set_of=SourceRun("random", seed, 0, ["v0", "v1"]))
        return run, final

    # seed 0: view t0 collapses with its depth at a tenth of the final-set's; t1 is a little nearer (0.9x: not near)
    r0, f0 = pair(0, [(14.0, 0.1), (21.0, 0.9)], [(24.0, 1.0), (20.0, 1.0)], "active (random at step 0)")
    # seed 1: no depth difference, the run 1 dB better on both views
    r1, f1 = pair(1, [(21.0, 1.0), (21.0, 1.0)], [(20.0, 1.0), (20.0, 1.0)], "active")
    out = done_when.near_views([r0, r1], [f0, f1])
    assert (out["views"], out["near"]) == (4, 1)
    assert out["near_mean"] == pytest.approx(-10.0) and out["rest_mean"] == pytest.approx(1.0)
    # costs: seed 0 22 - 17.5 = +4.5, seed 1 -1.0; with t0 at its final-set's 24 dB seed 0's is -0.5
    assert out["cost"] == pytest.approx(1.75) and out["cost_near_as_final_set"] == pytest.approx(-0.75)
    assert out["by_start"]["active (random at step 0)"] == {"pairs": 1, "near": 1, "views": 2, "cost": pytest.approx(4.5)}
    assert out["by_start"]["active"]["near"] == 0
    assert "front" not in out  # these runs did not record what lies in front of their cameras
    # where they did: the near view t0 has 3 large Gaussians in front (sigma up to 0.4, a quarter on a training
    # surface), its final-set none; the rest one view with one large (sigma 0.1, on a surface), two with none
    def front(view, large, sigma=None, on=None):
        extra = {"front_large_sigma_max": sigma, "front_large_on_surface": on,
                 "front_large_on_two_surfaces": on / 2, "front_large_in_view": on,
                 "front_large_suspect": 1 - on} if large else {}
        return dataclasses.replace(view, front_gaussians=large + 5, front_large=large, front_cover=0.1 * large, **extra)
    r0f = dataclasses.replace(r0, test_views=[front(r0.test_views[0], 3, 0.4, 0.25), front(r0.test_views[1], 1, 0.1, 1.0)])
    r1f = dataclasses.replace(r1, test_views=[front(v, 0) for v in r1.test_views])
    f0f = dataclasses.replace(f0, test_views=[front(v, 0) for v in f0.test_views])
    got = done_when.near_views([r0f, r1f], [f0f, f1])["front"]
    assert got["near"] == {"views": 1, "cover_mean": pytest.approx(0.3), "with_large": 1.0, "large_mean": 3.0,
                           "sigma_max_median": 0.4, "on_surface_mean": 0.25, "on_two_surfaces_mean": 0.125,
                           "in_view_mean": 0.25, "suspect_mean": 0.75}
    assert got["rest"] == {"views": 3, "cover_mean": pytest.approx(0.1 / 3), "with_large": pytest.approx(1 / 3),
                           "large_mean": pytest.approx(1 / 3), "sigma_max_median": 0.1, "on_surface_mean": 1.0,
                           "on_two_surfaces_mean": 0.5, "in_view_mean": 1.0, "suspect_mean": 0.0}
    assert got["near, final-set"] == {"views": 1, "cover_mean": 0.0, "with_large": 0.0, "large_mean": 0.0,
                                      "sigma_max_median": None, "on_surface_mean": None, "on_two_surfaces_mean": None,
                                      "in_view_mean": None, "suspect_mean": None}
    # runs written before depths were recorded: nothing to say
    bare = [dataclasses.replace(r, test_views=[dataclasses.replace(v, depth_p10=None) for v in r.test_views]) for r in (r0, r1)]
    assert done_when.near_views(bare, [f0, f1]) == {}


def test_near_culled_counts_runs_and_final_sets_apart(done_when):
    runs = [make_result("s1", "fisherrf", "random", k, 20.0, near_culled=c) for k, c in enumerate((10, 30))]
    finals = [make_result("s1", "fisherrf", "final-set", 0, 20.0, near_culled=4), make_result("s2", "fisherrf", "final-set", 0, 20.0)]
    out = done_when.culled_counts(runs, finals)
    assert out == {"runs": {"mean": 20, "min": 10, "max": 30, "runs": 2}, "final-sets": {"mean": 4, "min": 4, "max": 4, "runs": 1}}
    assert done_when.culled_counts([make_result()], []) == {}
