"""Every file the package writes goes through `atomic_path`: all or nothing, with the usual permissions."""

from __future__ import annotations

import json
import os

import pytest

from hpgs_ns.atomic_write import atomic_path, write_json_atomic


def test_json_written_whole_with_the_umask_permissions(tmp_path):
    path = write_json_atomic(tmp_path / "sub" / "run.json", {"psnr": 23.5})
    assert json.loads(path.read_text()) == {"psnr": 23.5}
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600
    assert [p.name for p in path.parent.iterdir()] == ["run.json"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    path = write_json_atomic(tmp_path / "run.json", {"old": True})
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            tmp.write_text('{"new": tr')  # killed half-way
            raise RuntimeError("killed")
    assert json.loads(path.read_text()) == {"old": True}
    assert [p.name for p in tmp_path.iterdir()] == ["run.json"]
