"""scripts/device_parts.py cuts a file into parts that scripts/device_env.sh's join_parts puts back together on the
GPU machine (sha256-checked); scripts/device_calls.py carries each part with its checksum file."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from helpers import load_script

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


@pytest.fixture(scope="module")
def parts():
    return load_script(SCRIPTS / "device_parts.py")


def join_in_bash(folder: Path, stem: str, dest: Path) -> subprocess.CompletedProcess:
    """device_env.sh's own join_parts function, run alone."""
    text = (SCRIPTS / "device_env.sh").read_text()
    function = re.search(r"^join_parts\(\) \{\n.*?^\}\n", text, re.S | re.M).group(0)
    script = f'{function}\njoin_parts "{folder}" "{folder}/{stem}.sha256" "{dest}"\n'
    return subprocess.run(["bash", "-c", script], capture_output=True, text=True)


def test_eleven_parts_join_back_in_order_and_a_new_cut_replaces_the_old(parts, tmp_path):
    data = bytes(range(256)) * 41 + b"tail"  # 10500 bytes: eleven parts of 955, the last shorter
    folder = tmp_path / "cut"
    paths = parts.split(data, folder, "w.whl", 11, "pkg-1.0-py3-none-any.whl")
    assert [p.name for p in paths][-2:] == ["w.whl.part-9", "w.whl.part-10"]
    assert [p.stat().st_size for p in paths] == [955] * 10 + [950]
    assert (folder / "w.whl.sha256").read_text().split()[1:] == ["11", "pkg-1.0-py3-none-any.whl"]
    assert parts.join(folder, "w.whl") == (data, "pkg-1.0-py3-none-any.whl")
    # bash sorts part-10 after part-9 too
    out = join_in_bash(folder, "w.whl", tmp_path / "joined")
    assert out.returncode == 0 and (tmp_path / "joined").read_bytes() == data
    # cut again into 3: the eleven old parts go, the checksum names 3
    parts.split(*parts.join(folder, "w.whl")[:1], folder, "w.whl", 3, "pkg-1.0-py3-none-any.whl")
    assert sorted(p.name for p in folder.glob("w.whl.part-*")) == ["w.whl.part-0", "w.whl.part-1", "w.whl.part-2"]
    assert parts.join(folder, "w.whl")[0] == data


def test_parts_that_do_not_join_are_named_and_nothing_is_written(parts, tmp_path):
    folder = tmp_path / "cut"
    parts.split(b"x" * 1000, folder, "v.ckpt", 4)
    (folder / "v.ckpt.part-2").write_bytes(b"y" * 250)
    with pytest.raises(parts.PartsError, match="do not join to .*v.ckpt.sha256's sha256"):
        parts.join(folder, "v.ckpt")
    out = join_in_bash(folder, "v.ckpt", tmp_path / "joined")
    assert "do not join to the recorded sha256" in out.stderr and not (tmp_path / "joined").exists()
    assert not list(tmp_path.glob("joined*"))  # the temp file is removed too
    (folder / "v.ckpt.part-3").unlink()
    with pytest.raises(parts.PartsError, match="names 4 parts, .* has 3"):
        parts.join(folder, "v.ckpt")
    # join_parts waits while parts are still to come
    out = join_in_bash(folder, "v.ckpt", tmp_path / "joined")
    assert out.returncode == 0 and out.stderr == "" and not (tmp_path / "joined").exists()


def test_the_planner_carries_each_part_with_its_checksum(tmp_path):
    calls = load_script(SCRIPTS / "device_calls.py")
    load_script(SCRIPTS / "device_parts.py").split(b"z" * 100, tmp_path / ".dev-vgg", "vgg16.ckpt", 12)
    units = calls.part_units(tmp_path, ".dev-vgg", "vgg16.ckpt")
    assert len(units) == 12 and units[10] == (".dev-vgg/vgg16.ckpt.part-10", ".dev-vgg/vgg16.ckpt.sha256")
    with pytest.raises(calls.CallsError, match="pyco/pycolmap.whl.sha256 is missing: run scripts/device_setup.sh"):
        calls.part_units(tmp_path, "pyco", "pycolmap.whl")
