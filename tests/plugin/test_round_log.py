"""The round log is written once per round, with everything the round did, and read back through `SelectionLog`."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import run_training, short_config

from hpgs_ns.selection.log import SelectionLog


@pytest.mark.parametrize("what", ["every-round", "at-views"])
def test_selected_views_json_is_written_once_per_round(tiny_scene, tmp_path, monkeypatch, what):
    writes = []
    original = SelectionLog.write

    def counted(self, path):
        writes.append((len(self.rounds), self.rounds[-1].to_dict() if self.rounds else None))
        return original(self, path)

    monkeypatch.setattr(SelectionLog, "write", counted)
    cfg = short_config(tiny_scene, tmp_path, steps=40, every=15, rounds=2, selector="random")
    if what == "every-round":
        cfg.pipeline.model.restarts.every_round = True
    else:  # a restart at the first round's 7 views only
        cfg.pipeline.model.restarts.at_views = (7,)
    trainer = run_training(cfg)
    # at the first step, once per round (15, 30), at the end: never a half-done round
    assert [n for n, _ in writes] == [0, 1, 2, 2]
    first, second = writes[1][1], writes[2][1]
    if what == "every-round":
        assert first["reset"] and first["num_gaussians_after_reset"] > 0 and "after_add" not in first
    else:
        assert first["reset"] and first["num_gaussians_after_reset"] > 0 and not second.get("reset")
    log = SelectionLog.read(Path(trainer.base_dir))
    assert [r.to_dict() for r in log.rounds] == [first, second]
    assert log.version == 2 and len(log.active) == 8 and log.chosen == [r["chosen"][0] for r in (first, second)]
