"""Which paths each device call carries, so that none passes the device tool's 64 MiB (working tree included).

Every call carries the working tree (tracked files and untracked ones git does not ignore) plus its `carry` list.
A lease's setup calls must bring: the wheels (`.dev/whl` cut into groups `.dev-whl/group-*`, each with the wheel
list and the prelude: `device_sweep.sh env` stages them and runs the prelude once all have come), the prebuilt
gsplat kernels (`.dev/prebuilt`, kept in /tmp), the
parts of pycolmap's wheel and of VGG16 (`.dev-pyco/pycolmap.whl.part-*`, `.dev-vgg/vgg16.ckpt.part-*`, each with its
`.sha256`: `scripts/device_env.sh` joins them once all have come; scripts/device_parts.py cuts them), AlexNet
(`.dev/extra`) and each scene's `.devdata/<folder>`. This packs them, largest first, into as few calls as fit
(first-fit). Prints one JSON carry list per call, with its size on disk.

    python scripts/device_calls.py --suite real12 --suite-scenes bonsai juicebox stitch [--limit-mib 63.0]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling script, also when loaded by a test
from device_parts import part_paths  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MIB = 2**20
WHEELS = ".dev/whl"
WHEEL_GROUPS = ".dev-whl"
WHEEL_COMPANIONS = ("prelude.sh", "sitecustomize.py")  # from .dev/, into every wheel group
MAX_PATHS = 8  # the device tool's limit on a call's carry list
PREBUILT = (".dev/prebuilt",)
VGG = (".dev-vgg", "vgg16.ckpt")
PYCOLMAP = (".dev-pyco", "pycolmap.whl")
ALEXNET = (".dev/extra",)


class CallsError(SystemExit):
    """One line naming what does not fit or is missing."""


def file_bytes(path: Path) -> int:
    """What a file takes on disk (whole blocks): the device tool's 64 MiB counts so (a call of 63.9 MiB of file
    contents, 67 MiB in blocks, was refused)."""
    return path.stat().st_blocks * 512


def size(path: Path) -> int:
    """Bytes of a file, or of every file under a folder; a missing path is an error naming its fix."""
    if not path.exists():
        raise CallsError(f"device_calls: {path} is missing: run scripts/device_setup.sh (and scripts/device_suite_data.py "
                         "for scenes) first")
    return file_bytes(path) if path.is_file() else sum(file_bytes(p) for p in path.rglob("*") if p.is_file())


def tree_bytes(repo: Path) -> int:
    """What every call carries anyway: tracked files and untracked files git does not ignore."""
    names = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=repo,
                           capture_output=True, check=True).stdout.decode().split("\0")
    return sum(file_bytes(repo / n) for n in names if n and (repo / n).is_file())


def part_units(repo: Path, folder: str, stem: str) -> List[Tuple[str, str]]:
    """A file cut by scripts/device_parts.py, as units: each part with the checksum file (device_env.sh joins the
    parts once the count the checksum names has come)."""
    sha = f"{folder}/{stem}.sha256"
    if not (repo / sha).is_file():
        raise CallsError(f"device_calls: {sha} is missing: run scripts/device_setup.sh")
    return [(f"{folder}/{p.name}", sha) for p in part_paths(repo / folder, stem)]


def wheel_groups(repo: Path, group_bytes: int = 8 * MIB) -> List[Tuple[str]]:
    """The wheels of .dev/whl cut into groups of at most `group_bytes` (largest first; a larger wheel alone), each a
    folder .dev-whl/group-<k>/ of hard links with whl.list (every wheel's name), prelude.sh and sitecustomize.py:
    scripts/device_wheels.sh stages them on the machine and runs the prelude once all have come. 25 MiB of wheels in
    one call left too little room beside a working tree of 35 MiB, and a call carries at most 8 paths, so not a
    wheel each. Rebuilt on every run from .dev/whl."""
    wheels = sorted((repo / WHEELS).glob("*.whl"), key=lambda p: (-file_bytes(p), p.name))
    if not wheels:
        raise CallsError(f"device_calls: no wheels in {WHEELS}: run scripts/device_setup.sh")
    groups: List[List[Path]] = []
    for wheel in wheels:
        room = next((g for g in groups if sum(map(file_bytes, g)) + file_bytes(wheel) <= group_bytes), None)
        if room is None:
            room = []
            groups.append(room)
        room.append(wheel)
    exclude = repo / ".git" / "info" / "exclude"  # the groups must not travel as untracked files in every call
    if exclude.parent.is_dir() and f"/{WHEEL_GROUPS}/" not in exclude.read_text().split():
        with open(exclude, "a") as f:
            f.write(f"/{WHEEL_GROUPS}/\n")
    out = repo / WHEEL_GROUPS
    if out.exists():
        shutil.rmtree(out)
    listing = "".join(f"{p.name}\n" for p in sorted(wheels, key=lambda p: p.name))
    for k, group in enumerate(groups):
        folder = out / f"group-{k}"
        folder.mkdir(parents=True)
        for wheel in group:
            try:
                os.link(wheel, folder / wheel.name)
            except OSError:  # another file system (or no hard links): a copy carries the same bytes
                shutil.copy2(wheel, folder / wheel.name)
        for name in WHEEL_COMPANIONS:
            shutil.copy2(repo / ".dev" / name, folder / name)
        (folder / "whl.list").write_text(listing)
    return [(f"{WHEEL_GROUPS}/group-{k}",) for k in range(len(groups))]


def pack(tree: int, limit: int, first: Sequence[str], units: Sequence[Sequence[str]],
         sizes: Dict[str, int], max_paths: int = MAX_PATHS) -> List[List[str]]:
    """Calls as carry lists: `first` opens the first call; each unit (paths that travel together, e.g. a half and
    its checksum) goes, largest first, into the first call with room, else into a new call at the end. A path
    already in a call costs nothing more there. Every call's tree + carry is at most `limit` bytes, and its carry
    list at most `max_paths` paths."""
    calls: List[List[str]] = [list(first)]

    def total(carry: Sequence[str]) -> int:
        return tree + sum(sizes[p] for p in dict.fromkeys(carry))

    if total(calls[0]) > limit:
        raise CallsError(f"device_calls: {' '.join(first)} with the working tree is {total(first) / MIB:.1f} MiB, over "
                         f"{limit / MIB:.1f}: ignore what the calls do not need (the tree is {tree / MIB:.1f} MiB)")
    for unit in sorted(units, key=lambda u: -sum(sizes[p] for p in u)):
        if total(unit) > limit:
            raise CallsError(f"device_calls: {' '.join(unit)} ({(total(unit) - tree) / MIB:.1f} MiB) does not fit a call "
                             f"beside the working tree ({tree / MIB:.1f} MiB) under {limit / MIB:.1f} MiB")
        room = next((c for c in calls if total([*c, *unit]) <= limit and len({*c, *unit}) <= max_paths), None)
        if room is None:
            room = []
            calls.append(room)
        room.extend(p for p in unit if p not in room)
    return calls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="real12")
    ap.add_argument("--suite-scenes", nargs="+", default=[], help="the scenes the lease runs (default: the suite's)")
    ap.add_argument("--data-root", type=Path, default=Path("../shared/data"))
    ap.add_argument("--limit-mib", type=float, default=63.0, help="a little under the tool's 64 MiB")
    ap.add_argument("--no-pycolmap", action="store_true", help="no run triangulates (no active start, no fox)")
    ap.add_argument("--no-vgg", action="store_true", help="no hpgs, condorcet or blend run")
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    from hpgs_lab.suites import load_suite

    scenes = [(f".devdata/{s.path.name}",) for s in load_suite(args.suite, args.data_root, args.suite_scenes) if not s.smoke]
    units = [*scenes, ALEXNET, PREBUILT, *wheel_groups(REPO), *(() if args.no_pycolmap else part_units(REPO, *PYCOLMAP)),
             *(() if args.no_vgg else part_units(REPO, *VGG))]
    sizes = {p: size(REPO / p) for p in {p for u in units for p in u}}
    tree = tree_bytes(REPO)
    calls = pack(tree, int(args.limit_mib * MIB), (), units, sizes)
    print(f"working tree {tree / MIB:.1f} MiB on disk; {len(calls)} calls, each `bash scripts/device_sweep.sh env` "
          "(the last may be the launch call: it keeps what it carries before the runs start):")
    for carry in calls:
        print(f"{(tree + sum(sizes[p] for p in carry)) / MIB:5.1f} MiB  {json.dumps(carry)}")


if __name__ == "__main__":
    main()
