"""benchmarks/candidate_scores.py, the offline analysis of `--log-candidate-scores` runs (the blend's weights), and
how `hpgs bench` keeps a run's candidate log for it."""

from __future__ import annotations

import gzip
import json
import sys

import numpy as np
from conftest import REPO


def test_the_analysis_fits_the_combination_leaving_one_scene_out(tmp_path):
    sys.path.insert(0, str(REPO / "benchmarks"))
    from candidate_scores import leave_one_scene_out, load_rounds, summarize

    rng = np.random.default_rng(0)
    for scene in ("a", "b", "c"):
        # as hpgs bench keeps them (gzip), and one scene as an older plain .jsonl
        path = tmp_path / scene / "fisherrf" / "random" / f"seed0-candidates.jsonl{'' if scene == 'c' else '.gz'}"
        path.parent.mkdir(parents=True)
        with (open(path, "w") if scene == "c" else gzip.open(path, "wt")) as f:
            for _ in range(4):
                error = rng.random(20)
                scores = {"fisher": list(error + 0.1 * rng.random(20)), "farthest": list(rng.random(20))}
                f.write(json.dumps({"scores": scores, "oracle": {"lpips": list(error)}}) + "\n")
    rounds = load_rounds(tmp_path)
    assert len(rounds) == 12 and {r["scene"] for r in rounds} == {"a", "b", "c"}
    per = summarize(rounds, ["farthest", "fisher"])
    assert per["fisher"]["spearman"] > 0.9 > abs(per["farthest"]["spearman"]) and per["fisher"]["top_percentile"] >= 0.9
    loso = leave_one_scene_out(rounds, ["farthest", "fisher"])
    assert set(loso["per_scene"]) == {"a", "b", "c"}
    assert all(w["fisher"] > 5 * abs(w["farthest"]) for w in loso["weights"].values())  # learnt on the other scenes
    assert loso["held_out_mean"]["spearman"] > 0.9


def test_bench_keeps_a_runs_log_gzipped_and_the_analysis_reads_it(tmp_path):
    sys.path.insert(0, str(REPO / "benchmarks"))
    from candidate_scores import load_rounds

    from hpgs_lab.runs import keep_candidate_log

    log = tmp_path / "run" / "candidate_scores.jsonl"
    log.parent.mkdir()
    lines = [{"scores": {"farthest": [0.1, 0.9]}, "oracle": {"lpips": [0.2, 0.3]}, "round": k} for k in range(3)]
    log.write_text("".join(json.dumps(x) + "\n" for x in lines))
    keep = tmp_path / "out" / "s" / "fisherrf" / "farthest" / "seed1-candidates.jsonl.gz"
    keep_candidate_log(log, keep)
    (keep.parent / "seed1.json").write_text(json.dumps({"seed": 1}))
    assert sorted(p.name for p in keep.parent.iterdir()) == ["seed1-candidates.jsonl.gz", "seed1.json"]  # no temp
    rounds = load_rounds(tmp_path / "out")
    assert [r["round"] for r in rounds] == [0, 1, 2] and {(r["scene"], r["seed"]) for r in rounds} == {("s", 1)}
