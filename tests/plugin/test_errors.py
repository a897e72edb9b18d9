"""Fixable failures print as one line (`error: ...`) under nerfstudio's CLIs and `hpgs`; others keep tracebacks."""

from __future__ import annotations

import subprocess
import sys

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
