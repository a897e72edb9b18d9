"""Fixable failures print as one line (`error: ...`) under nerfstudio's CLIs and `hpgs`; others keep tracebacks.

The excepthook is installed in every `ns-*` process (nerfstudio imports every method's module): it speaks for the
plugin's `UserError`s and for load failures of hpgs runs only; anything else, another method's run included, reaches
the hook before it untouched (#66).
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from hpgs_ns.datamanager import ActiveViewError
from hpgs_ns.dataparser import SceneDataError
from hpgs_ns.errors import UserError, print_user_errors
from hpgs_ns.selectors import SelectionError


def test_user_errors_print_one_line_and_others_fall_through(capsys, monkeypatch):
    fallen = []
    fallback = lambda *args: fallen.append(args[0])  # noqa: E731
    print_user_errors(SelectionError, SelectionError("empty candidate pool; lower --max-rounds"), None, fallback)
    assert capsys.readouterr().err == "error: empty candidate pool; lower --max-rounds\n" and not fallen
    print_user_errors(KeyError, KeyError("bug"), None, fallback)
    assert fallen == [KeyError]
    monkeypatch.setenv("HPGS_TRACEBACK", "1")
    print_user_errors(ActiveViewError, ActiveViewError("x"), None, fallback)
    assert fallen == [KeyError, ActiveViewError]
    # Still the built-in kinds callers catch.
    assert issubclass(SceneDataError, ValueError) and issubclass(SelectionError, RuntimeError)
    assert issubclass(SceneDataError, UserError)


def test_ns_train_with_a_bad_path_prints_the_fix_without_a_traceback(tmp_path):
    cmd = [sys.executable, "-m", "nerfstudio.scripts.train", "hpgs", "--data", str(tmp_path / "nope"),
           "--output-dir", str(tmp_path / "out"), "--vis", "tensorboard", "--pipeline.model.rasterizer", "cpu"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr + proc.stdout
    last = proc.stderr.strip().splitlines()[-1]
    assert last == f"error: scene folder {tmp_path / 'nope'} does not exist; pass --data PATH to a Mip-NeRF 360 style scene"
    assert list((tmp_path / "out").rglob("*")) == []  # the run folder ns-train made before set-up failed is gone


# ---- #66: the hook speaks only for the plugin ---------------------------------------------------------------------

UNRELATED = """
def fail():
    try:
        {}["key"]
    except KeyError as err:
        raise RuntimeError("x") from err
fail()
"""


def test_an_unrelated_exception_prints_exactly_as_without_the_plugin():
    """The same script, with and without the import that installs the hook (line 1 of both, so every line number
    agrees): the traceback from `Traceback` on is the same, byte for byte."""
    with_plugin = "import sys, hpgs_ns.method_config; print(sys.excepthook.hpgs_user_errors)" + UNRELATED
    without = "import sys" + UNRELATED
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
            for code in (with_plugin, without)]
    assert runs[0].stdout == "True\n"  # the hook is installed: it let the exception through
    assert [run.returncode for run in runs] == [1, 1]
    tracebacks = [run.stderr[run.stderr.index("Traceback (most recent call last):"):] for run in runs]
    assert tracebacks[0] == tracebacks[1] and tracebacks[1].endswith("RuntimeError: x\n")
    assert "KeyError: 'key'" in tracebacks[1] and "error: " not in runs[0].stderr


def test_ns_train_hpgs_num_initial_views_0_is_still_one_line(tmp_path):
    """An OptionError raised while tyro parses the command line: before any trainer or run folder exists."""
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "nerfstudio.scripts.train", "hpgs", "--data", str(tmp_path), "--output-dir", str(out),
           "--vis", "tensorboard", "--pipeline.model.rasterizer", "cpu", "--pipeline.datamanager.num-initial-views", "0"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1].startswith("error: --pipeline.datamanager.num-initial-views 0: must be "
                                                            "at least 1")
    assert "Traceback" not in proc.stderr + proc.stdout and not out.exists()


# A config.yml cut or edited so that yaml cannot build it (a tag naming no class): one of another method's runs, and
# one of the plugin's (its tags name hpgs_ns classes, as the first line of every hpgs run's config.yml does).
STOCK = """!!python/object:nerfstudio.engine.trainer.TrainerConfig
method_name: splatfacto
pipeline: !!python/object:nerfstudio.pipelines.base_pipeline.NoSuchPipelineConfig
  _target: !!python/name:nerfstudio.pipelines.base_pipeline.VanillaPipeline ''
"""
HPGS = """!!python/object:hpgs_ns.trainer.HpgsTrainerConfig
method_name: hpgs
pipeline: !!python/object:hpgs_ns.pipeline.NoSuchPipelineConfig
  _target: !!python/name:hpgs_ns.pipeline.HpgsPipeline ''
"""


def hook_output(err: BaseException):
    """(what the installed hook's logic prints to stderr, what it handed to the hook before it) for `err`."""
    import io

    fallen = []
    real, sys.stderr = sys.stderr, io.StringIO()
    try:
        print_user_errors(type(err), err, err.__traceback__, lambda *args: fallen.append(args))
        printed = sys.stderr.getvalue()
    finally:
        sys.stderr = real
    return printed, fallen


@pytest.mark.parametrize("cli", ["eval", "viewer"])
def test_a_damaged_config_of_another_method_s_run_keeps_nerfstudio_s_traceback(tmp_path, monkeypatch, cli):
    import importlib

    import hpgs_ns.method_config  # noqa: F401 (what every ns-* process imports: the hook and its explainer)

    module = importlib.import_module("nerfstudio.scripts.eval" if cli == "eval" else "nerfstudio.scripts.viewer.run_viewer")
    if hasattr(module, "_start_viewer"):  # a hang guard: a viewer that did open the run would serve forever
        monkeypatch.setattr(module, "_start_viewer", lambda *a: pytest.fail("ns-viewer loaded the run and started"))
    for name, text in (("stock", STOCK), ("hpgs", HPGS)):
        config = tmp_path / name / "config.yml"
        config.parent.mkdir()
        config.write_text(text)
        monkeypatch.setattr(sys, "argv", [f"ns-{cli}", "--load-config", str(config)])
        with pytest.raises(yaml.constructor.ConstructorError) as info:
            module.entrypoint()
        printed, fallen = hook_output(info.value)
        if name == "stock":  # the same exception, traceback and all, to the hook before (Python's: the traceback)
            assert printed == "" and fallen == [(type(info.value), info.value, info.value.__traceback__)]
        else:
            assert not fallen and printed.startswith(f"error: {config} is not a readable run config (ConstructorError: ")
            assert printed.count("\n") == 1


def test_an_empty_checkpoint_folder_is_one_line_for_an_hpgs_run_only(tmp_path, monkeypatch):
    """nerfstudio's IndexError (no step-*.ckpt) and ValueError (a file there that is not one) when it picks the
    newest checkpoint: named for a run whose config.yml is the plugin's, nerfstudio's own for a splatfacto run."""
    from nerfstudio.utils.eval_utils import eval_load_checkpoint

    import hpgs_ns.method_config  # noqa: F401

    empty = tmp_path / "nerfstudio_models"
    empty.mkdir()
    config = type("Config", (), {"load_dir": empty, "load_step": None})()
    for text, one_line in ((STOCK, False), (HPGS, True)):
        (tmp_path / "config.yml").write_text(text)
        monkeypatch.setattr(sys, "argv", ["ns-eval", "--load-config", str(tmp_path / "config.yml")])
        for notes in (False, True):
            if notes:
                (empty / "notes.txt").write_text("mine")
            with pytest.raises((IndexError, ValueError)) as info:
                eval_load_checkpoint(config, None)
            printed, fallen = hook_output(info.value)
            if not one_line:
                assert printed == "" and [args[1] for args in fallen] == [info.value]
            elif notes:
                assert printed == (f"error: {empty} holds files that are not checkpoints (notes.txt), and nerfstudio "
                                   "reads every file there as one: move them out of it\n")
            else:
                assert printed == (f"error: {empty} holds no checkpoint (step-*.ckpt); train the run first (it saves one "
                                   "every --steps-per-save steps and at its last), or copy the run's nerfstudio_models there\n")
        (empty / "notes.txt").unlink()
    # a --load-config that is missing or a folder without config.yml names no run: nerfstudio's own message
    from hpgs_ns.run_config import names_the_plugin

    assert not names_the_plugin(tmp_path / "nope.yml") and not names_the_plugin(empty) and names_the_plugin(tmp_path)
