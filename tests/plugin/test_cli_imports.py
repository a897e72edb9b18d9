"""`hpgs --help` and `hpgs CMD --help` load neither torch nor nerfstudio, and print no warning (cli.py's promise).

Checked in a fresh interpreter (`sys.modules` after the fact): this test process has long imported both. How long
the help takes is a benchmark's business (benchmarks/help_time.py), not a test's.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hpgs_ns import cli

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "nerfstudio")

# Runs in a fresh interpreter: import hpgs_ns.cli, print `hpgs --help`, then `hpgs CMD --help` for every command in
# turn; after each step, which of HEAVY are loaded, what warnings were raised, the exit status and the output size.
PROBE = """
import contextlib, io, json, sys, warnings
HEAVY = %r
def loaded():
    return sorted(m for m in HEAVY if m in sys.modules)
steps = []
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    import hpgs_ns.cli as cli
    steps.append({"step": "import hpgs_ns.cli", "loaded": loaded(), "code": 0, "chars": 0})
    for args in [["--help"]] + [[name, "--help"] for name in cli.COMMANDS]:
        out, code = io.StringIO(), 0
        sys.argv = ["hpgs", *args]
        with contextlib.redirect_stdout(out):
            try:
                cli.entrypoint()
            except SystemExit as exit:
                code = exit.code or 0
        steps.append({"step": "hpgs " + " ".join(args), "loaded": loaded(), "code": code, "chars": len(out.getvalue())})
warnings_seen = [f"{w.category.__name__}: {w.message} ({w.filename}:{w.lineno})" for w in caught]
print(json.dumps({"steps": steps, "warnings": warnings_seen}))
"""


@pytest.fixture(scope="module")
def probe() -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "100"}
    proc = subprocess.run([sys.executable, "-c", PROBE % (HEAVY,)], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]) | {"stderr": proc.stderr}


def test_import_and_top_level_help_load_neither_torch_nor_nerfstudio(probe):
    first, top = probe["steps"][0], probe["steps"][1]
    assert first == {"step": "import hpgs_ns.cli", "loaded": [], "code": 0, "chars": 0}
    assert top["step"] == "hpgs --help" and top["code"] == 0 and top["chars"] > 0
    assert top["loaded"] == [], "hpgs --help loaded " + ", ".join(top["loaded"])


def test_every_command_help_loads_neither_torch_nor_nerfstudio(probe):
    steps = probe["steps"][2:]
    assert [s["step"] for s in steps] == [f"hpgs {name} --help" for name in cli.COMMANDS]
    assert all(s["code"] == 0 and s["chars"] > 0 for s in steps), steps
    # the first step that pulls one in (later steps inherit it)
    culprit = next((s for s in probe["steps"] if s["loaded"]), None)
    assert culprit is None, f"`{culprit['step']}` loaded {', '.join(culprit['loaded'])}"


def test_help_prints_no_warning(probe):
    assert probe["warnings"] == []
    assert probe["stderr"] == ""


def test_top_level_help_lists_every_command_with_its_docstring_summary():
    """`hpgs --help` reads each Command's summary instead of importing the commands: they must say what the
    docstrings say. (The lab's `bench`: tests/lab/test_lab_cli.py.)"""
    for name, command in cli.COMMANDS.items():
        doc = (command.load().__doc__ or "").strip().splitlines()
        assert command.summary == (doc[0] if doc else ""), name
    usage = cli.usage()
    assert all(f"  {name:<12} {command.summary}" in usage for name, command in cli.COMMANDS.items())


def test_preference_recipe_names_are_the_model_s():
    """The light `recipe` module and `model` share one set of objects (tyro's choices, the caught error)."""
    from hpgs_ns.preference import model, recipe

    assert model.BackboneName is recipe.BackboneName and model.FeatureTransform is recipe.FeatureTransform
    assert model.PreferenceModelError is recipe.PreferenceModelError


# Runs in a fresh interpreter, argv: the heavy modules to look for. Which are loaded after reading the registry's
# names, order and default alone. (With the lab's defaults and rows on top, as `hpgs bench --help` reads them:
# tests/lab/test_lab_cli.py.)
REGISTRY_PROBE = """
import json, sys
heavy = sys.argv[1:]
from hpgs_ns.selectors import registry
names, default = registry.selector_names(), registry.DEFAULT_SELECTOR
alone = sorted(m for m in heavy + ["tyro"] if m in sys.modules)
print(json.dumps({"alone": alone, "names": names, "default": default, "builtin": list(registry.BUILTIN_SELECTORS)}))
"""


def test_the_selector_names_load_neither_torch_nor_nerfstudio():
    """The registry is the one list of selector names: reading them, their order and the default imports no torch,
    nerfstudio or tyro; a config class is imported only when it is asked for."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", REGISTRY_PROBE, *HEAVY], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    found = json.loads(proc.stdout.strip().splitlines()[-1])
    assert found["alone"] == [], found
    assert found["builtin"] == found["names"][:len(found["builtin"])]
    assert found["default"] in found["builtin"]
