"""`--pipeline.selection.log-candidate-scores`: every selector's score of every candidate at each round, beside
each candidate's render error, without changing the run; and the offline analysis that reads the logs."""

from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import torch
from conftest import run_training, short_config

from hpgs_ns.selection.candidate_log import logged_selectors


def seeded_run(scene: Path, out: Path, log: bool):
    random.seed(0), np.random.seed(0), torch.manual_seed(0)  # as ns-train's --machine.seed does
    cfg = short_config(scene, out, steps=24, every=20, rounds=1, selector="random", log_candidate_scores=log)
    cfg.pipeline.selection.fisher.probes = 2
    return run_training(cfg)


def test_the_log_holds_every_selector_and_the_oracle_and_changes_nothing(tiny_scene, tmp_path):
    logged = seeded_run(tiny_scene, tmp_path / "logged", True)
    plain = seeded_run(tiny_scene, tmp_path / "plain", False)
    lines = (Path(logged.base_dir) / "candidate_scores.jsonl").read_text().splitlines()
    assert len(lines) == 1 and not (Path(plain.base_dir) / "candidate_scores.jsonl").exists()
    line = json.loads(lines[0])
    assert line["step"] == 20 and line["chosen"][0] in line["candidates"] and line["chosen"][0] not in line["active"]
    n = len(line["candidates"])
    assert len(line["active"]) == 6 and n == 35 - 6
    assert sorted(line["scores"]) == sorted(logged_selectors())  # every selector whose config says it is logged
    assert all(len(v) == n and all(np.isfinite(v)) for v in line["scores"].values())
    assert all(len(v) == n and all(np.isfinite(v)) for v in line["oracle"].values())
    assert 5 < min(line["oracle"]["psnr"]) and max(line["oracle"]["lpips"]) <= 1
    # the run itself is the same: same pick, same Gaussians
    a, b = logged.pipeline, plain.pipeline
    assert a.datamanager.history[0].chosen == b.datamanager.history[0].chosen
    for name, value in a.model.gauss_params.items():
        assert torch.equal(value, b.model.gauss_params[name]), name
