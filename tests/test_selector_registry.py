"""One selector registry: the datamanager's choices and option groups, `hpgs bench`, the README, and selectors
that other packages register through the `hpgs_ns.selectors` entry point group."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
import textwrap
import typing
from pathlib import Path

import pytest

from conftest import REPO, run_training, short_config
from hpgs_ns.datamanager import ActiveDatamanagerConfig
from hpgs_ns.selectors import BUILTIN_SELECTORS, SelectionError, SelectorConfig, selector_config, selector_names

TOY = textwrap.dedent('''
    """A third-party selector: always the candidate with the highest index."""
    from dataclasses import dataclass, field
    from typing import Type

    from hpgs_ns.selectors.base import Selection, SelectorConfig


    class LastSelector:
        def __init__(self, config):
            self.config = config

        def select(self, context):
            picked = sorted(context.candidates)[-context.num_to_pick:]
            return Selection(indices=picked, scores={c: float(c) for c in context.candidates})


    @dataclass
    class LastSelectorConfig(SelectorConfig):
        _target: Type = field(default_factory=lambda: LastSelector)
''')


@pytest.fixture
def toy_plugin(tmp_path, monkeypatch) -> Path:
    """An installed package `toy_selector` whose entry point registers the selector `last`."""
    (tmp_path / "toy_selector.py").write_text(TOY)
    info = tmp_path / "toy_selector-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-selector\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[hpgs_ns.selectors]\nlast = toy_selector:LastSelectorConfig\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_option_groups_and_choices_list_exactly_the_builtin_selectors():
    groups = [f.name for f in dataclasses.fields(ActiveDatamanagerConfig)
              if isinstance(f.default_factory, type) and issubclass(f.default_factory, SelectorConfig)]
    assert groups == list(BUILTIN_SELECTORS)
    for name, cls in BUILTIN_SELECTORS.items():
        assert type(getattr(ActiveDatamanagerConfig(), name)) is cls
    choices = typing.get_args(typing.get_type_hints(ActiveDatamanagerConfig)["selector"])
    assert list(choices) == selector_names()[: len(choices)] and set(BUILTIN_SELECTORS) <= set(choices)


def test_bench_and_the_readme_read_the_registry():
    from hpgs_ns.bench.protocols import DEFAULT_SELECTORS, row_order
    from hpgs_ns.bench.runs import Bench

    assert list(DEFAULT_SELECTORS) == Bench().selectors == list(BUILTIN_SELECTORS)
    assert row_order()[: len(BUILTIN_SELECTORS)] == list(BUILTIN_SELECTORS)
    readme = (REPO / "README.md").read_text()
    table = readme[readme.index("## The selectors"):]
    table = table[: table.index("\n\n", table.index("| name |"))]
    assert sorted(re.findall(r"^\| `([\w-]+)` \|", table, re.M)) == sorted(BUILTIN_SELECTORS)


def test_unknown_selector_is_a_one_line_error():
    with pytest.raises(SelectionError, match="unknown selector 'nope'; choose one of random, farthest"):
        selector_config("nope")


def test_an_entry_point_selector_runs_a_round(toy_plugin, tiny_scene, tmp_path):
    assert "last" in selector_names()
    assert type(selector_config("last")).__name__ == "LastSelectorConfig"
    cfg = short_config(tiny_scene, tmp_path, steps=25, every=20, rounds=1, selector="last")
    run_dir = Path(run_training(cfg).base_dir)
    log = json.loads((run_dir / "selected_views.json").read_text())
    assert [r["selector"] for r in log["rounds"]] == ["last"]
    assert log["rounds"][0]["chosen"] == [max(log["withheld"] + log["rounds"][0]["chosen"])]


def test_ns_train_offers_an_entry_point_selector_on_the_command_line(toy_plugin):
    code = ("import tyro; from hpgs_ns.datamanager import ActiveDatamanagerConfig as C; "
            "print(tyro.cli(C, args=['--selector', 'last']).selector_config().__class__.__name__)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(toy_plugin), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "LastSelectorConfig"
