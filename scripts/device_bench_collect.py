"""Put bench JSON fetched from the device (`files_at` of a `scripts/device_bench_queue.sh` call) where
`hpgs bench` keeps it: `OUT/<scene>/<protocol>/<selector>/seed<k>.json`, from the run's own fields (the fetched
names are flattened). A run already there with other contents is left alone and reported.

    python scripts/device_bench_collect.py /work/.device/7 [--out benchmarks/results/bench]
"""

import argparse
import json
import shutil
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fetched", type=Path, help="folder with the fetched seed JSON files")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/bench"))
    args = parser.parse_args()
    for src in sorted(args.fetched.glob("*.json")):
        run = json.loads(src.read_text())
        dest = args.out / run["scene"] / run["protocol"] / run["selector"] / f"seed{run['seed']}.json"
        if dest.exists():
            print(f"{'same' if dest.read_bytes() == src.read_bytes() else 'DIFFERENT, kept'}: {dest}")
            continue
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dest)
        print(f"new: {dest}  PSNR {run['test']['psnr']:.2f}")


if __name__ == "__main__":
    main()
