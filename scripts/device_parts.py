"""Cut a file into N parts that ride in separate device calls (each call carries at most 64 MiB, the working tree
included), with a checksum file `scripts/device_env.sh` reads to join them on the machine.

Layout in FOLDER: `STEM.part-0 .. STEM.part-{N-1}` and `STEM.sha256` = "<sha256 of the whole> <N> [<file name>]"
(the name, when given, is what the joined file is called: pip reads a wheel's version and platform from it).

    python scripts/device_parts.py split FILE FOLDER STEM --parts 4 [--keep-name]
    python scripts/device_parts.py resplit FOLDER STEM --parts 4     # join what is there (checked), cut again
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path
from typing import List, Optional

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script (device_setup.sh): the repo's modules
from hpgs_ns.atomic_write import atomic_path  # noqa: E402


class PartsError(SystemExit):
    """One line naming the parts that do not join, and the fix."""


def part_paths(folder: Path, stem: str) -> List[Path]:
    """The parts in their order (part-10 after part-9)."""
    return sorted(folder.glob(f"{stem}.part-*"), key=lambda p: int(p.name.rsplit("-", 1)[1]))


def write_atomic(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def split(data: bytes, folder: Path, stem: str, parts: int, name: Optional[str] = None) -> List[Path]:
    """Write `data` as `parts` nearly equal parts and the checksum file; parts of an earlier cut are removed first."""
    if parts < 1:
        raise PartsError(f"device_parts: --parts {parts} must be >= 1")
    folder.mkdir(parents=True, exist_ok=True)
    for old in part_paths(folder, stem):
        old.unlink()
    size = -(-len(data) // parts)
    out = []
    for i in range(parts):
        path = folder / f"{stem}.part-{i}"
        write_atomic(path, data[i * size:(i + 1) * size])
        out.append(path)
    line = f"{hashlib.sha256(data).hexdigest()} {parts}" + (f" {name}" if name else "")
    write_atomic(folder / f"{stem}.sha256", (line + "\n").encode())
    return out


def join(folder: Path, stem: str) -> tuple[bytes, Optional[str]]:
    """The whole file from its parts, checked against the checksum file; (data, its recorded name or None)."""
    sha_file = folder / f"{stem}.sha256"
    if not sha_file.is_file():
        raise PartsError(f"device_parts: {sha_file} is missing: run scripts/device_setup.sh")
    words = sha_file.read_text().split()
    sha, count, name = words[0], int(words[1]), (words[2] if len(words) > 2 else None)
    paths = part_paths(folder, stem)
    if len(paths) != count:
        raise PartsError(f"device_parts: {sha_file} names {count} parts, {folder} has {len(paths)}: "
                         "delete the folder and run scripts/device_setup.sh")
    data = b"".join(p.read_bytes() for p in paths)
    if hashlib.sha256(data).hexdigest() != sha:
        raise PartsError(f"device_parts: the parts in {folder} do not join to {sha_file}'s sha256: delete the folder "
                         "and run scripts/device_setup.sh")
    return data, name


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    one = sub.add_parser("split", help="cut FILE into FOLDER/STEM.part-*")
    one.add_argument("file", type=Path)
    one.add_argument("folder", type=Path)
    one.add_argument("stem")
    one.add_argument("--parts", type=int, default=4)
    one.add_argument("--keep-name", action="store_true", help="record FILE's name (a wheel's)")
    again = sub.add_parser("resplit", help="join FOLDER/STEM.part-* (checked) and cut it into --parts")
    again.add_argument("folder", type=Path)
    again.add_argument("stem")
    again.add_argument("--parts", type=int, default=4)
    args = ap.parse_args()
    if args.command == "split":
        paths = split(args.file.read_bytes(), args.folder, args.stem, args.parts,
                      args.file.name if args.keep_name else None)
    else:
        data, name = join(args.folder, args.stem)
        paths = split(data, args.folder, args.stem, args.parts, name)
    print(f"device_parts: {len(paths)} parts of {args.stem} in {args.folder}")


if __name__ == "__main__":
    main()
