"""Test PSNR against training step for the final-set references (a run's 20 views trained from step 0), one line per
scene and start: where the fit of 20 views peaks, and how far it falls after.

    python benchmarks/plot_final_set_curves.py [--out docs/final-set-curves.png] [ROOT ...]

ROOT defaults to benchmarks/results/tune-full and benchmarks/results/judge-full (<scene>/<start>/final-set/seed0.json,
whose `psnr_at_round_steps` holds the test PSNR at the protocol's round steps). Prints each curve's peak and final
value and writes the figures as JSON beside the PNG.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from hpgs_ns.atomic_write import atomic_path, write_json_atomic  # noqa: E402

ROOTS = [Path("benchmarks/results/tune-full"), Path("benchmarks/results/judge-full")]


def curves(roots):
    """[(scene, start, [(step, psnr)] ending with the final PSNR)] for every seed-0 final-set under `roots`."""
    out = []
    for root in roots:
        for path in sorted(root.glob("*/*/final-set/seed0.json")):
            data = json.loads(path.read_text())
            points = sorted((int(k), float(v)) for k, v in (data.get("psnr_at_round_steps") or {}).items())
            if points:
                start, scene = path.parent.parent.name, path.parent.parent.parent.name
                out.append((scene, start, points + [(int(data["steps"]), float(data["test"]["psnr"]))]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("roots", nargs="*", type=Path, default=ROOTS)
    parser.add_argument("--out", type=Path, default=Path("docs/final-set-curves.png"))
    args = parser.parse_args()
    found = curves(args.roots)
    if not found:
        raise SystemExit(f"no final-set runs with a PSNR curve under {' '.join(map(str, args.roots))}")
    starts = sorted({start for _, start, _ in found})
    fig, axes = plt.subplots(1, len(starts), figsize=(6 * len(starts), 4.2), squeeze=False, sharey=True)
    rows = []
    for ax, start in zip(axes[0], starts):
        for scene, s, points in found:
            if s != start:
                continue
            steps, psnr = zip(*points)
            peak = max(points, key=lambda p: p[1])
            ax.plot(steps, psnr, marker=".", label=f"{scene} (peak {peak[1]:.1f} @ {peak[0]}, end {psnr[-1]:.1f})")
            rows.append({"scene": scene, "start": start, "peak_step": peak[0], "peak_psnr": peak[1], "final_psnr": psnr[-1]})
            print(f"{start:7s} {scene:16s} peak {peak[1]:6.2f} dB at step {peak[0]:5d}; end {psnr[-1]:6.2f} "
                  f"({psnr[-1] - peak[1]:+.2f})")
        ax.set_title(f"final-set (20 views from step 0), `{start}` start")
        ax.set_xlabel("training step")
        ax.set_xscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("test PSNR (dB)")
    fig.tight_layout()
    with atomic_path(args.out, suffix=args.out.suffix) as tmp:
        fig.savefig(tmp, dpi=110)
    write_json_atomic(args.out.with_suffix(".json"), rows)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
