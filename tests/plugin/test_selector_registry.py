"""One selector registry: the selection options' choices and groups (and their 0.2 spelling), `hpgs bench`, the
candidate log, provenance, the README, and selectors that other packages register through the `hpgs_ns.selectors`
entry point group."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import REPO, run_training, short_config

from hpgs_ns.selectors import SelectionError
from hpgs_ns.selectors.registry import BUILTIN_SELECTORS, selector_class, selector_config, selector_names


def parse_pipeline(args):
    """`ns-train hpgs`'s pipeline options as tyro reads them (in-process)."""
    import tyro

    from hpgs_ns.method_config import hpgs_trainer_config

    default = hpgs_trainer_config(100).pipeline
    return tyro.cli(type(default), default=default, args=args)


def test_selection_options_parse_and_the_0_2_spelling_is_gone():
    new = parse_pipeline(["--selection.selector", "fisher", "--selection.fisher.probes", "3",
                          "--selection.select-every", "50"])
    assert (new.selection.selector, new.selection.fisher.probes, new.selection.select_every) == ("fisher", 3, 50)
    with pytest.raises(SystemExit):  # dropped at 0.4 (the changelog says so); old config.yml files still read
        parse_pipeline(["--datamanager.selector", "fisher"])


def test_the_readme_lists_every_builtin_selector():
    readme = (REPO / "README.md").read_text()
    table = readme[readme.index("## The selectors"):]
    table = table[: table.index("\n\n", table.index("| name |"))]
    assert sorted(re.findall(r"^\| `([\w-]+)` \|", table, re.M)) == sorted(BUILTIN_SELECTORS)


def test_a_plugin_selector_reaches_the_candidate_log(toy_plugin):
    from hpgs_ns.selection.candidate_log import logged_selectors

    # every selector whose config says its scores say something, the plugin's too (by SelectorConfig's default);
    # random's scores are all equal, blend is a mix
    logged = logged_selectors()
    assert logged == [name for name in selector_names() if selector_class(name).logged_in_candidate_log]
    assert logged[-1] == "last" and not {"random", "blend"} & set(logged)


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


def test_ns_train_offers_an_entry_point_selector_and_its_options_on_the_command_line(toy_plugin, tmp_path):
    """A selector of another package: chosen, and one of its options set, from `ns-train hpgs`'s command line, as
    ns-train parses it (a new process, which reads the entry points as nerfstudio does)."""
    code = textwrap.dedent("""
        import sys, tyro
        from hpgs_ns.method_config import hpgs_trainer_config
        default = hpgs_trainer_config(100)
        config = tyro.cli(type(default), default=default, args=sys.argv[1:])
        options = config.pipeline.selection.selector_config()
        print(type(options).__name__, options.keep_last, config.pipeline.selection.selector)
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(toy_plugin), str(REPO), os.environ.get("PYTHONPATH", "")])}
    args = ["--pipeline.selection.selector", "last", "--pipeline.selection.last.keep-last", "3"]
    out = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "LastSelectorConfig 3 last"
    help_text = subprocess.run([sys.executable, "-c", code, "--help"], env=env, capture_output=True, text=True,
                               timeout=180).stdout
    assert "--pipeline.selection.last.keep-last" in help_text


def test_a_run_without_rounds_never_builds_its_selector(monkeypatch):
    """A final-set run (`max-rounds 0`) with the default `hpgs` selector loads no preference model."""
    from types import SimpleNamespace

    from hpgs_ns.selection.config import SelectionConfig
    from hpgs_ns.selectors import hpgs as hpgs_selector

    def no_model(*_args, **_kwargs):
        raise AssertionError("the preference model was loaded")

    monkeypatch.setattr(hpgs_selector, "load_preference_model", no_model)
    datamanager = SimpleNamespace(config=SimpleNamespace(seed=0))
    SelectionConfig(selector="hpgs", max_rounds=0).setup(datamanager=datamanager, model=None)
    with pytest.raises(AssertionError, match="the preference model was loaded"):
        SelectionConfig(selector="hpgs", max_rounds=1).setup(datamanager=datamanager, model=None)


def test_options_of_a_selector_the_run_does_not_use_say_at_start_that_they_do_nothing(tiny_scene, tmp_path, capsys):
    # the default is `farthest`: a preference model given without `--pipeline.selection.selector hpgs` would be
    # silently ignored
    parsed = parse_pipeline(["--selection.hpgs.model", "kitchen.pt", "--selection.fisher.probes", "3"])
    assert parsed.selection.idle_selector_options() == ["--pipeline.selection.fisher.probes",
                                                        "--pipeline.selection.hpgs.model"]
    assert parse_pipeline(["--selection.selector", "hpgs", "--selection.hpgs.model", "kitchen.pt"]
                          ).selection.idle_selector_options() == []
    assert parse_pipeline(["--selection.hpgs.model", "kitchen.pt", "--selection.log-candidate-scores"]
                          ).selection.idle_selector_options() == []  # the candidate log scores with every selector
    cfg = short_config(tiny_scene, tmp_path, steps=2, rounds=0)
    cfg.pipeline.selection.hpgs.model = tmp_path / "kitchen.pt"
    run_training(cfg)
    out = " ".join(capsys.readouterr().out.split())
    assert ("--pipeline.selection.hpgs.model does nothing in this run: the selector is farthest "
            "(add --pipeline.selection.selector hpgs)") in out


NEW_BUILTIN = textwrap.dedent('''
    """A new built-in selector as a test writes one: its module (this file) and one registry line, nothing else."""
    from dataclasses import dataclass, field
    from typing import Type

    from hpgs_ns.selectors.base import Selection, SelectorConfig


    class LowestIndexSelector:
        def __init__(self, config):
            self.config = config

        def select(self, context):
            return Selection(indices=sorted(context.candidates)[:context.num_to_pick])


    @dataclass
    class LowestIndexSelectorConfig(SelectorConfig):
        """Always the candidates with the lowest index."""

        _target: Type = field(default_factory=lambda: LowestIndexSelector)
        skip: int = 0
        """An option of the new selector."""
''')

# In a fresh interpreter: the new selector's one registry line, then everything that lists selectors is built as in
# any process (the selection config's groups and ns-train's choices, the candidate log, `hpgs bench`'s defaults).
NEW_BUILTIN_PROBE = textwrap.dedent("""
    import contextlib, io, json
    from hpgs_ns.selectors import registry
    registry.BUILTIN_SELECTORS["lowest-index"] = "lowest_index:LowestIndexSelectorConfig"  # the one registry line

    import tyro
    from hpgs_lab.protocols import DEFAULT_SELECTORS
    from hpgs_lab.runs import Bench
    from hpgs_ns.method_config import hpgs_trainer_config
    from hpgs_ns.selection.candidate_log import logged_selectors

    def help_of(cls, **kwargs):
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
            tyro.cli(cls, args=["--help"], **kwargs)
        return out.getvalue()

    default = hpgs_trainer_config(100)
    args = ["--pipeline.selection.selector", "lowest-index", "--pipeline.selection.lowest-index.skip", "2"]
    options = tyro.cli(type(default), default=default, args=args).pipeline.selection.selector_config()
    print(json.dumps({
        "names": registry.selector_names(), "options": [type(options).__name__, options.skip],
        "ns_train_help": help_of(type(default), default=default), "logged": logged_selectors(),
        "choices": registry.SelectorName.__metadata__[0].metavar,
        "bench_defaults": list(DEFAULT_SELECTORS), "bench_selectors": Bench().selectors,
        "bench_help": help_of(Bench, prog="hpgs bench"),
    }))
""")


def test_a_new_builtin_selector_is_its_module_and_one_registry_line(tmp_path):
    (tmp_path / "lowest_index.py").write_text(NEW_BUILTIN)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO), os.environ.get("PYTHONPATH", "")]),
           "COLUMNS": "400"}
    out = subprocess.run([sys.executable, "-c", NEW_BUILTIN_PROBE], env=env, cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    found = json.loads(out.stdout.strip().splitlines()[-1])
    assert found["names"][:len(BUILTIN_SELECTORS) + 1] == [*BUILTIN_SELECTORS, "lowest-index"]
    assert found["options"] == ["LowestIndexSelectorConfig", 2]  # chosen, and its option group parsed
    assert "--pipeline.selection.lowest-index.skip" in found["ns_train_help"]
    assert found["choices"] == "{" + ",".join([*BUILTIN_SELECTORS, "lowest-index"]) + "}"  # as the help shows them
    assert "lowest-index" in found["logged"]  # SelectorConfig's default facts
    assert found["bench_defaults"] == found["bench_selectors"] == [*BUILTIN_SELECTORS, "lowest-index"]
    assert " ".join([*BUILTIN_SELECTORS, "lowest-index"]) in " ".join(found["bench_help"].split())


def test_a_preset_s_flags_are_named_by_its_registry_line():
    from hpgs_ns.errors import OptionError
    from hpgs_ns.selectors.shortlist import ShortlistPresetConfig

    presets = [name for name in BUILTIN_SELECTORS if issubclass(selector_class(name), ShortlistPresetConfig)]
    assert presets
    for name in presets:
        assert selector_class(name).preset_name() == name
        with pytest.raises(OptionError, match=re.escape(f"--pipeline.selection.{name}.shortlist-size 2")):
            selector_class(name)(shortlist_size=2.0)
