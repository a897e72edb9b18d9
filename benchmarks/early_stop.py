"""The early-stop curve (views saved against PSNR lost over `stop-when-gain-below` X) and the shipped gain model.

Reads benchmark runs (their test PSNR before every round), judges each scene with a gain model fitted on the
other scenes (leave one scene out), and fits the model shipped in hpgs_ns/assets/gain-model.json on all of them:

    python benchmarks/early_stop.py benchmarks/results/suite --out benchmarks/results/early_stop.json \
        --plot benchmarks/results/early_stop.png [--write-model hpgs_ns/assets/gain-model.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hpgs_lab.gain_fit import early_stop_curve, fit_gain_model
from hpgs_lab.results import load_results

THRESHOLDS = (-0.5, -0.25, 0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.5, 1.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--write-model", type=Path, default=None)
    args = ap.parse_args()
    rows = [r for r in load_results(args.results) if not r.smoke and not r.repeat]
    curve = early_stop_curve(rows, THRESHOLDS)
    model = fit_gain_model(rows)
    print(f"{curve[0]['runs']} runs, scenes {', '.join(model.fitted_on)} (each judged with a model fitted on the others)")
    print("| stop below (dB) | views saved per run | test PSNR lost (dB, pessimistic) |\n|---|---|---|")
    for c in curve:
        print(f"| {c['threshold_db']:g} | {c['views_saved']:.1f} | {c['psnr_lost_db']:.2f} |")
    args.out.write_text(json.dumps({"curve": curve, "model_all_scenes": {k: list(v) for k, v in model.coefficients.items()},
                                    "scenes": model.fitted_on}, indent=1) + "\n")
    if args.write_model:
        model.save(args.write_model)
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.6))
        ax.plot([c["views_saved"] for c in curve], [c["psnr_lost_db"] for c in curve], marker="o")
        for c in curve:
            ax.annotate(f"{c['threshold_db']:g}", (c["views_saved"], c["psnr_lost_db"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        ax.set(xlabel="views saved per run", ylabel="test PSNR lost (dB)",
               title="stop-when-gain-below X (labels: X in dB), leave one scene out")
        ax.title.set_fontsize(9)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)


if __name__ == "__main__":
    main()
