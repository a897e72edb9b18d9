"""Preference-model accuracy on the real HP-GS human labels (Mip-NeRF 360 garden, 55 renders, 1485 pairs).

Protocol: grouped k-fold over *images*. The 55 images are shuffled into k folds; for each fold the model is
trained (exactly as `hpgs train-pref` with a frozen backbone: cached features, L-BFGS head fit) on the pairs
whose two images are both outside the fold, and tested on the pairs whose two images are both inside it, so
every test pair shows two images never seen in training and every image is held out once. Pairs across the
split are unused in that fold. Repeated with `--repeats` shuffles; the table gives mean and std over repeats.

Baselines on the same test pairs: the constant answer "Image_1 is worse"; sharpness (variance of the
Laplacian of the grey image, lower = worse; no training); and the ceiling of any per-image score, ranking by
each image's human win count over all 1485 pairs (in-sample, so an upper bound; ties count half).

    PYTHONPATH=. .venv/bin/python benchmarks/pref_garden_cv.py [--folds 5 --repeats 4]

prints the table and writes benchmarks/results/pref_garden_cv.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Dict, List

import torch
import torch.nn.functional as F

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hpgs_ns.offline_weights import cached_resnet34_weights  # noqa: E402
from hpgs_ns.preference.evaluate import index_pairs, pair_accuracy_from_scores, raw_features_of  # noqa: E402
from hpgs_ns.preference.model import BackboneUnavailable, PreferenceModel  # noqa: E402
from hpgs_ns.preference.pairs import image_folds, load_image, read_usable_pairs  # noqa: E402
from hpgs_ns.preference.train import TrainPref, fit_head_and_score  # noqa: E402


def laplacian_variance(image: torch.Tensor) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image ([3, H, W] in [0, 1]); low = blurry."""
    grey = (0.299 * image[0] + 0.587 * image[1] + 0.114 * image[2])[None, None]
    kernel = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]])[None, None]
    return float(F.conv2d(grey, kernel).var())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="hpgs-pairs-garden folder (default: shared/)")
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--l2", type=float, default=0.1)
    parser.add_argument("--backbones", nargs="*", default=["alexnet", "vgg16", "efficientnet-lite0", "resnet34"])
    parser.add_argument("--finetune", nargs="*", default=[], metavar="BACKBONE",
                        help="also fine-tune these backbones per fold (minibatch, augmented; slow on a CPU)")
    parser.add_argument("--finetune-epochs", type=int, default=3)
    parser.add_argument("--finetune-repeats", type=int, default=1)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "pref_garden_cv.json")
    args = parser.parse_args()

    shared = Path(os.environ.get("HPGS_SHARED", REPO / ".." / "shared"))
    data = args.data or shared / "data" / "hpgs-pairs-garden"
    if not (data / "pairs.csv").is_file():
        raise SystemExit(f"pref_garden_cv: {data / 'pairs.csv'} not found; pass --data or set HPGS_SHARED")
    torch.set_num_threads(min(4, os.cpu_count() or 1))
    pairs = read_usable_pairs([data / "pairs.csv"])
    images, index, labels = index_pairs(pairs)
    pos = {p: i for i, p in enumerate(images)}

    # The test pairs of every (repeat, fold): both images inside the fold.
    splits = []
    for repeat in range(args.repeats):
        for fold in image_folds(images, args.folds, seed=repeat):
            inside = torch.zeros(len(images), dtype=torch.bool)
            inside[[pos[p] for p in fold]] = True
            test = inside[index[:, 0]] & inside[index[:, 1]]
            train = ~inside[index[:, 0]] & ~inside[index[:, 1]]
            splits.append((repeat, train, test))

    def cv(score_fn, repeats: int = args.repeats) -> Dict[str, float]:
        """Accuracy pooled over the folds of each repeat; score_fn(train_mask) -> per-image scores [N]."""
        per_repeat: Dict[int, List[float]] = {}
        for repeat, train, test in splits:
            if repeat >= repeats:
                continue
            scores = score_fn(train)
            right = pair_accuracy_from_scores(scores, index[test], labels[test]) * int(test.sum())
            per_repeat.setdefault(repeat, []).append((right, int(test.sum())))
        accs = [sum(r for r, _ in v) / sum(n for _, n in v) for v in per_repeat.values()]
        return {"accuracy": statistics.mean(accs), "std": statistics.pstdev(accs),
                "test_pairs_per_repeat": sum(n for _, n in next(iter(per_repeat.values())))}

    rows: Dict[str, Dict] = {}
    # Constant answer: the test pairs' share of label 1 (its scores would be all ties, so compute directly).
    per_repeat: Dict[int, List] = {}
    for repeat, _, test in splits:
        per_repeat.setdefault(repeat, []).append((int(labels[test].sum()), int(test.sum())))
    const = [sum(r for r, _ in v) / sum(n for _, n in v) for v in per_repeat.values()]
    rows["constant: Image_1 is worse"] = {"accuracy": statistics.mean(const), "std": statistics.pstdev(const),
                                          "test_pairs_per_repeat": sum(n for _, n in per_repeat[0])}

    sharp = torch.tensor([laplacian_variance(load_image(p)) for p in images])
    rows["sharpness (Laplacian variance)"] = cv(lambda train: -sharp)

    wins = torch.zeros(len(images))
    for (i1, i2), y in zip(index.tolist(), labels.tolist()):
        wins[i1 if y == 1 else i2] += 1
    rows["ceiling: human win counts (in-sample)"] = cv(lambda train: wins)
    all_pairs_ceiling = pair_accuracy_from_scores(wins, index, labels)

    timings = {}
    for name in args.backbones:
        t0 = time.time()
        try:
            model = PreferenceModel(name, pretrained=True, input_size=args.input_size).eval()
        except BackboneUnavailable as err:
            rows[f"{name} (frozen)"] = {"accuracy": None, "note": str(err)}
            print(f"{name}: skipped: {err}", file=sys.stderr)
            continue
        raw = raw_features_of(model, images, batch_size=16)

        def learned(train: torch.Tensor, model=model, raw=raw) -> torch.Tensor:
            return fit_head_and_score(model, raw, index[train], labels[train], l2=args.l2)

        rows[f"{name} (frozen)"] = cv(learned)
        rows[f"{name} (frozen)"]["feature_dim"] = model.feature_dim
        timings[name] = round(time.time() - t0, 1)

    for name in args.finetune:
        t0 = time.time()
        pretrained = "none" if name == "resnet34" and cached_resnet34_weights() is None else "imagenet"
        recipe = TrainPref(pairs=(), out=Path("unused"), backbone=name, pretrained=pretrained, finetune=True,
                           epochs=args.finetune_epochs, input_size=args.input_size, l2=args.l2)

        def finetuned(train: torch.Tensor, recipe=recipe) -> torch.Tensor:
            model, _, _ = recipe.fit([p for p, t in zip(pairs, train.tolist()) if t])
            with torch.no_grad():
                return model.score_features(model.standardise(raw_features_of(model, images, progress=False)))

        key = f"{name} (fine-tuned, {args.finetune_epochs} epochs{', from scratch' if pretrained == 'none' else ''})"
        rows[key] = cv(finetuned, repeats=args.finetune_repeats)
        timings[key] = round(time.time() - t0, 1)
        print(f"{key}: {rows[key]['accuracy']:.1%}", file=sys.stderr)

    width = max(map(len, rows))
    print(f"\nHP-GS garden labels: {len(pairs)} pairs, {len(images)} images; grouped {args.folds}-fold over images "
          f"(test pairs: both images held out), {args.repeats} repeats")
    print(f"{'method':<{width}}  accuracy   std    test pairs/repeat")
    for name, row in rows.items():
        if row.get("accuracy") is None:
            print(f"{name:<{width}}  {'n/a':>8}   ({row['note'][:70]}...)")
            continue
        print(f"{name:<{width}}  {row['accuracy']:8.1%}  {row['std']:5.1%}   {row['test_pairs_per_repeat']}")
    print(f"{'ceiling on all 1485 pairs':<{width}}  {all_pairs_ceiling:8.1%}")

    result = {
        "data": str(data), "pairs": len(pairs), "images": len(images),
        "protocol": {"scheme": "grouped k-fold over images; test pairs have both images held out, train pairs "
                               "neither; every image held out once per repeat",
                     "folds": args.folds, "repeats": args.repeats, "input_size": args.input_size, "l2": args.l2,
                     "finetune_epochs": args.finetune_epochs, "finetune_repeats": args.finetune_repeats},
        "rows": rows, "ceiling_all_pairs": all_pairs_ceiling, "seconds": timings,
        "torch": torch.__version__, "machine": platform.machine(), "threads": torch.get_num_threads(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    os.replace(tmp, args.out)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
