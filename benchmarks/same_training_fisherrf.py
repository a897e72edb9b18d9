"""One tiny FisherRF-protocol `farthest` run (CPU rasterizer, the default trainer) with whichever hpgs_ns is first on
sys.path, its numbers as JSON: run it on two commits to check that they train the default path identically
(complements benchmarks/same_numbers.py, whose runs are 60-step HP-GS-style rounds).

    git worktree add /tmp/old COMMIT
    PYTHONPATH=/tmp/old python benchmarks/same_training_fisherrf.py --scene /tmp/ring --out /tmp/old.json \
        [--random-init] [--seed-points active]
    python benchmarks/same_training_fisherrf.py --scene /tmp/ring --out /tmp/new.json --compare /tmp/old.json

The scene: `hpgs_ns.scenes.synthetic.make_scene(Path("/tmp/ring"), layout="ring", num_cameras=40, width=64,
height=48, num_points=1500, seed=0)` (made once, shared by both runs). `--compare` exits 1 unless the chosen
views and every per-round and test PSNR/SSIM/LPIPS are equal.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from hpgs_ns.atomic_write import write_json_atomic


def main() -> None:
    import hpgs_ns
    from hpgs_lab.runs import Bench

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--random-init", action="store_true", help="random points (restarts at 8 and 16 views)")
    parser.add_argument("--seed-points", default=None, help="--pipeline.datamanager.seed-points (default: the trainer's)")
    parser.add_argument("--compare", type=Path, default=None)
    args = parser.parse_args()
    extra = "--pipeline.model.num-downscales 0" + (" --pipeline.model.random-init True" if args.random_init else "")
    extra += f" --pipeline.datamanager.seed-points {args.seed_points}" if args.seed_points else ""
    with tempfile.TemporaryDirectory() as tmp:
        bench = Bench(scenes=[args.scene], out=Path(tmp), selectors=["farthest"], seeds=[args.seed],
                      protocols=["fisherrf"], step_scale=0.01, initial_views=4, rasterizer="cpu", references=False,
                      extra_args=extra)
        bench.run_all(bench.scene_list())
        [path] = sorted(Path(tmp).glob("*/fisherrf/farthest/seed*.json"))
        data = json.loads(path.read_text())
    keep = {k: data["test"][k] for k in ("psnr", "ssim", "lpips")}
    result = {"package": str(Path(hpgs_ns.__file__).parent), "seed": args.seed, "random_init": args.random_init,
              "seed_points": args.seed_points,
              "test": keep, "chosen": data["chosen_views"], "psnr_per_round": data["psnr_per_round"]}
    write_json_atomic(args.out, result)
    print(json.dumps(keep))
    if args.compare is not None:
        before = json.loads(args.compare.read_text())
        same = all(before[k] == result[k] for k in ("test", "chosen", "psnr_per_round"))
        print("same views and numbers" if same else f"differs from {args.compare}")
        sys.exit(0 if same else 1)


if __name__ == "__main__":
    main()
