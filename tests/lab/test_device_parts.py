"""scripts/device_parts.py cuts a file into parts that scripts/device_env.sh's join_parts puts back together on the
GPU machine (sha256-checked); scripts/device_calls.py carries each part with its checksum file."""

from __future__ import annotations

import re
import shutil
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


def fake_dev(repo: Path, sizes_kib) -> list:
    (repo / ".git" / "info").mkdir(parents=True)
    (repo / ".git" / "info" / "exclude").write_text("/.dev/\n")
    (repo / ".dev" / "whl").mkdir(parents=True)
    (repo / ".dev" / "prelude.sh").write_text("touch prelude-ran\n")
    (repo / ".dev" / "sitecustomize.py").write_text("")
    names = []
    for i, kib in enumerate(sizes_kib):
        names.append(f"w{i}-1.0-py3-none-any.whl")
        (repo / ".dev" / "whl" / names[-1]).write_bytes(b"w" * kib * 1024)
    return names


def test_the_wheels_go_in_groups_each_with_the_list_and_the_prelude(tmp_path):
    calls = load_script(SCRIPTS / "device_calls.py")
    names = fake_dev(tmp_path, [7000, 3000, 3000, 2000, 9000, 100])
    units = calls.wheel_groups(tmp_path, group_bytes=8 * 2**20)
    groups = [tmp_path / u[0] for u in units]
    carried = [p.name for g in groups for p in g.glob("*.whl")]
    assert sorted(carried) == sorted(names)  # every wheel once
    for g in groups:
        sizes = [p.stat().st_size for p in g.glob("*.whl")]
        assert sum(sizes) <= 8 * 2**20 or len(sizes) == 1  # a wheel larger than a group goes alone
        assert (g / "whl.list").read_text().split() == sorted(names)
        assert (g / "prelude.sh").is_file() and (g / "sitecustomize.py").is_file()
    assert "/.dev-whl/" in (tmp_path / ".git" / "info" / "exclude").read_text().split()  # never travels as untracked
    assert len(calls.wheel_groups(tmp_path, group_bytes=8 * 2**20)) == len(units)  # rebuilt, not added to
    # a call carries at most 8 paths
    out = calls.pack(0, 100, (), [(f"p{i}",) for i in range(20)], {f"p{i}": 1 for i in range(20)})
    assert [len(c) for c in out] == [8, 8, 4]


def stage(call: Path, stage_root: Path) -> subprocess.CompletedProcess:
    script = f'source "{SCRIPTS / "device_wheels.sh"}"; stage_wheels "{stage_root}"; rc=$?; wheels_carried "{stage_root}"; exit $rc'
    return subprocess.run(["bash", "-c", script], cwd=call, capture_output=True, text=True)


def test_the_machine_stages_the_wheels_until_every_group_has_come(tmp_path):
    calls = load_script(SCRIPTS / "device_calls.py")
    repo = tmp_path / "repo"
    names = fake_dev(repo, [5000, 5000, 5000])
    units = calls.wheel_groups(repo, group_bytes=6 * 2**20)
    assert len(units) == 3
    where = tmp_path / "stage"
    for k, (unit,) in enumerate(units):  # one call each: only what it carries is in its working tree
        call = tmp_path / f"call{k}"
        shutil.copytree(repo / unit, call / unit)
        out = stage(call, where)
        assert out.stdout.strip() == f"{k + 1} of 3 wheels"
        assert out.returncode == (0 if k == 2 else 1), out
    assert sorted(p.name for p in (where / ".dev" / "whl").iterdir()) == sorted(names)
    assert (where / ".dev" / "prelude.sh").is_file()
    # a whole .dev as before (wheels and prelude, no list) is complete at once
    old = tmp_path / "old"
    shutil.copytree(repo / ".dev", old / ".dev")
    assert stage(old, tmp_path / "stage-old").returncode == 0
