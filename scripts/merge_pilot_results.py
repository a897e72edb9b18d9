"""Put a device pilot's results into a results folder: every `seed<k>.json` under each SRC (a sweep's `--out`, as
`scripts/device_arm_sweeps.sh` leaves them in `OUT/s<seed>/<arm>`), at the same relative path under INTO, its
`_runs/` working folders skipped. A file already at INTO with other content is not overwritten (the run is named
and the merge stops before copying anything), so a repeat of a pilot cannot quietly replace its first results.

    python scripts/merge_pilot_results.py /tmp/pilot/s0/reset /tmp/pilot/s1/reset /tmp/pilot/s2/reset \
        --into benchmarks/results/tune-boost/auto/reset
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import List, Tuple

from hpgs_ns.atomic_write import atomic_path


def plan(sources: List[Path], into: Path) -> Tuple[List[Tuple[Path, Path]], List[str]]:
    """(the (source, destination) copies to make, the destinations that already hold other content)."""
    copies, clashes = [], []
    for src in sources:
        for path in sorted(src.rglob("seed*.json")):
            rel = path.relative_to(src)
            if "_runs" in rel.parts:
                continue
            dest = into / rel
            if dest.exists():
                if dest.read_bytes() != path.read_bytes():
                    clashes.append(str(dest))
                continue
            copies.append((path, dest))
    return copies, clashes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sources", type=Path, nargs="+")
    ap.add_argument("--into", type=Path, required=True)
    args = ap.parse_args()
    missing = [str(s) for s in args.sources if not s.is_dir()]
    if missing:
        print(f"merge_pilot_results: no such folder: {', '.join(missing)} (unpack the pilot's tarball first)", file=sys.stderr)
        return 2
    copies, clashes = plan(args.sources, args.into)
    if clashes:
        print(f"merge_pilot_results: {len(clashes)} result(s) already in {args.into} with other content, e.g. {clashes[0]}; "
              "nothing copied (merge into another folder, or remove those first)", file=sys.stderr)
        return 1
    for src, dest in copies:
        dest.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(dest) as tmp:
            shutil.copyfile(src, tmp)
    print(f"merge_pilot_results: {len(copies)} result(s) copied into {args.into}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
