"""`hpgs bench` as the plugin's `hpgs` finds it: the lab registers it through the `hpgs.commands` entry point group
(pyproject.toml), and without that registration `hpgs bench` says in one line how to get the lab. The entry point
lookup is monkeypatched: the venv's installed metadata may be another checkout's."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from importlib import metadata

import pytest
from conftest import REPO
from helpers import lab_commands_env

from hpgs_lab import cli as lab_cli
from hpgs_ns import cli


def declared(group: str = cli.ENTRY_POINT_GROUP) -> metadata.EntryPoints:
    """The entry points of `group` as pyproject.toml declares them (what `pip install -e .` would register)."""
    spec = lab_commands_env()["HPGS_COMMANDS"]
    return metadata.EntryPoints(metadata.EntryPoint(name, value, group)
                                for name, _, value in (item.partition("=") for item in spec.split(",")))


@pytest.fixture
def installed(monkeypatch):
    """As after `pip install -e .` of this checkout."""
    monkeypatch.delenv(cli.COMMANDS_ENV, raising=False)
    monkeypatch.setattr(metadata, "entry_points", lambda group=None: declared() if group == cli.ENTRY_POINT_GROUP else ())


@pytest.fixture
def not_installed(monkeypatch):
    """The plugin without the lab: nothing in the group."""
    monkeypatch.delenv(cli.COMMANDS_ENV, raising=False)
    monkeypatch.setattr(metadata, "entry_points", lambda group=None: metadata.EntryPoints(()))


def run_hpgs(monkeypatch, capsys, *args: str):
    monkeypatch.setattr(sys, "argv", ["hpgs", *args])
    code = 0
    try:
        cli.entrypoint()
    except SystemExit as exit:
        code = exit.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_pyproject_registers_bench_as_the_labs_command():
    assert [(ep.name, ep.value) for ep in declared()] == [("bench", "hpgs_lab.cli:bench")]
    command = declared()["bench"].load()
    assert command is lab_cli.bench and isinstance(command, cli.Command)
    doc = command.load().__doc__.strip().splitlines()[0]
    assert command.summary == doc  # `hpgs --help` prints the summary without importing hpgs_lab.runs


def test_an_installed_lab_adds_bench_to_hpgs(installed, monkeypatch, capsys):
    assert cli.registered_commands() == {"bench": lab_cli.bench}
    code, out, _ = run_hpgs(monkeypatch, capsys, "--help")
    assert code == 0 and f"  {'bench':<12} {lab_cli.bench.summary}" in out and "suggest" in out
    code, out, _ = run_hpgs(monkeypatch, capsys, "bench", "--help")
    assert code == 0 and "usage: hpgs bench" in out and "--suite" in out


def test_without_the_lab_hpgs_bench_is_one_line_naming_the_install(not_installed, monkeypatch, capsys):
    assert cli.registered_commands() == {}
    code, out, err = run_hpgs(monkeypatch, capsys, "bench", "--suite", "real6")
    assert code == 1 and out == ""
    assert err.count("\n") == 1 and err.startswith("hpgs bench needs the benchmark package") and "pip install -e ." in err
    assert "hpgs_lab" not in err  # the plugin names no package of the lab
    code, out, _ = run_hpgs(monkeypatch, capsys, "--help")  # the plugin's commands are all still there
    assert code == 0 and "bench" not in out and all(name in out for name in cli.COMMANDS)
    code, _, err = run_hpgs(monkeypatch, capsys, "nope")
    assert code == 2 and "unknown command 'nope'" in err


def test_hpgs_commands_registers_the_lab_in_a_checkout_that_is_not_installed(not_installed, monkeypatch):
    monkeypatch.setenv(cli.COMMANDS_ENV, lab_commands_env()["HPGS_COMMANDS"])
    assert cli.registered_commands() == {"bench": lab_cli.bench}
    monkeypatch.setenv(cli.COMMANDS_ENV, "demo=hpgs_lab.cli:bench,gone=hpgs_gone.cli:x")
    assert cli.registered_commands() == {}  # the plugin's names are its own; a package gone since is not registered


def test_hpgs_bench_help_in_a_fresh_interpreter_loads_neither_torch_nor_nerfstudio():
    probe = ("import json, sys, contextlib, io; import hpgs_ns.cli as cli; sys.argv = ['hpgs', 'bench', '--help']\n"
             "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
             "    try:\n        cli.entrypoint()\n    except SystemExit as e:\n        code = e.code or 0\n"
             "print(json.dumps({'code': code, 'chars': len(out.getvalue()),"
             " 'loaded': sorted(m for m in ('torch', 'nerfstudio') if m in sys.modules)}))")
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "100", **lab_commands_env()}
    proc = subprocess.run([sys.executable, "-c", probe], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["code"] == 0 and result["chars"] > 1000 and result["loaded"] == []
    assert proc.stderr == ""  # no warning


def test_bench_default_selectors_are_the_registry_built_ins():
    """The lab's protocols write the built-in selector names out (importing the registry loads torch)."""
    from hpgs_lab.protocols import DEFAULT_SELECTORS
    from hpgs_ns.selectors.registry import BUILTIN_SELECTORS

    assert DEFAULT_SELECTORS == tuple(BUILTIN_SELECTORS)


# Runs in a fresh interpreter, argv: the heavy modules to look for. Which are loaded after the lab's defaults and rows
# (what `hpgs bench --help` reads); the registry's names alone: tests/plugin/test_cli_imports.py.
LAB_SELECTORS_PROBE = """
import json, sys
heavy = sys.argv[1:]
from hpgs_ns.selectors import registry
names = registry.selector_names()
from hpgs_lab.protocols import DEFAULT_SELECTORS, row_order
row_order()
print(json.dumps({"with_lab": sorted(m for m in heavy if m in sys.modules), "names": names,
                  "bench": list(DEFAULT_SELECTORS), "builtin": list(registry.BUILTIN_SELECTORS)}))
"""


def test_the_labs_selector_defaults_and_rows_load_neither_torch_nor_nerfstudio():
    """`hpgs bench --help` reads the lab's default selectors and row order: through the registry's names, without
    torch or nerfstudio; the defaults are the registry's built-ins, in its order."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", LAB_SELECTORS_PROBE, "torch", "nerfstudio"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    found = json.loads(proc.stdout.strip().splitlines()[-1])
    assert found["with_lab"] == [], found
    assert found["bench"] == found["builtin"] == found["names"][:len(found["builtin"])]
