"""A preference model that generalises: choose its recipe leave one scene out on oracle-labelled renders, then
score the HP-GS human labels of garden once.

Input: `hpgs collect` folders of several scenes (renders/ and renders.csv: each render's PSNR/SSIM/LPIPS against
its photo). Every render pair of a scene gets an oracle label from LPIPS (the one with the higher LPIPS is
worse), so no person and no garden label is involved. For each recipe (backbone, L2 penalty on the head, which
pairs train it, the least LPIPS difference a training pair must have) and each scene S, a head is fitted on the
other scenes' pairs and scored on S's pairs; the recipe with the best mean over scenes wins. Backbones may be
joined (`alexnet+vgg16`: both trunks' pooled features concatenated) and each trunk's features transformed
(`--transforms`, see hpgs_ns/preference/model.py). Held-out pairs are
of two kinds: any two renders, and two views at the same training step (what a selector compares, and what the
garden labels are: renders of one partially trained splat); `--choose-by` says which one picks the recipe.
Only then is the winner, trained on every oracle scene, scored on garden's human labels (never seen in training
or in the choice). With --write-model it is saved with that record.

    hpgs collect --data SCENE --out pref/SCENE ...           # for each scene (GPU, or CPU at small size)
    python benchmarks/pref_loso.py pref/juicebox pref/stitch ... --out benchmarks/results/pref_loso.json \\
        [--write-model hpgs_ns/assets/preference-default.pt] [--no-garden]

`--no-garden` stops after the choice: use it for trial runs, so garden is scored once, for the recipe shipped.

Frozen backbones only (the head is fitted on cached features with L-BFGS: `hpgs_ns.preference.train.fit_head`),
so a recipe costs seconds once the features are computed.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import itertools
import json
import os
import random
import statistics
import sys
import time
from pathlib import Path
from typing import Dict, List, Tuple

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hpgs_ns.atomic_write import atomic_path, write_text_atomic  # noqa: E402
from hpgs_ns.preference.evaluate import index_pairs, pair_accuracy_from_scores, raw_features_of  # noqa: E402
from hpgs_ns.preference.model import BACKBONES, FEATURE_TRANSFORMS, PreferenceModel, transform_pooled  # noqa: E402
from hpgs_ns.preference.pairs import read_usable_pairs  # noqa: E402
from hpgs_ns.preference.train import fit_head_and_score  # noqa: E402

Render = Tuple[Path, int, str, float]  # (image, training step, view, LPIPS against its photo)


def read_renders(folder: Path) -> List[Render]:
    with open(folder / "renders.csv", newline="", encoding="utf-8") as f:
        return [(folder / r["image"], int(r["step"]), r["view"], float(r["lpips"])) for r in csv.DictReader(f)]


def oracle_pairs(renders: List[Render], n: int, same_step: bool, seed: int, margin: float = 0.0) -> List[Tuple[int, int, int]]:
    """n random pairs (i, j, label: 1 = i worse by LPIPS); `same_step`: both renders from one training step
    (different views at one moment, as a selector compares candidates). Pairs whose LPIPS differ by no more than
    `margin` (ties, and near-ties whose oracle label is a coin flip) are dropped."""
    rng = random.Random(seed)
    if same_step:
        by_step: Dict[int, List[int]] = {}
        for k, r in enumerate(renders):
            by_step.setdefault(r[1], []).append(k)
        pool = [p for ks in by_step.values() for p in itertools.combinations(ks, 2)]
    else:
        pool = list(itertools.combinations(range(len(renders)), 2))
    out = []
    for i, j in rng.sample(pool, min(n, len(pool))):
        if abs(renders[i][3] - renders[j][3]) > margin:
            out.append((i, j, int(renders[i][3] > renders[j][3])))
    return out


def recipe_features(trunk_features: Dict[str, torch.Tensor], backbone: str, transform: str) -> torch.Tensor:
    """A recipe's raw features from its trunks' untransformed ones: what PreferenceModel(backbone,
    feature_transform=transform).raw_features computes (tests/lab/test_pref_loso.py checks they agree)."""
    return torch.cat([transform_pooled(trunk_features[t], transform) for t in backbone.split("+")], dim=1)


def trunk_features_of(trunks: List[str], paths: List[Path], cache: Path | None) -> Dict[str, torch.Tensor]:
    """Untransformed raw features of every trunk, from `cache` when there."""
    out = {}
    for trunk in trunks:
        t0 = time.time()
        out[trunk] = cached_features(PreferenceModel(trunk, pretrained=True).eval(), trunk, paths, cache)
        print(f"{trunk}: features of {len(paths)} images in {time.time() - t0:.0f} s")
    return out


def cached_features(model: PreferenceModel, backbone: str, paths: List[Path], cache: Path | None) -> torch.Tensor:
    """`raw_features_of` for these images, kept under `cache` keyed by backbone and the images' paths, sizes and
    mtimes: a frozen backbone's features (~30 min of CPU for vgg16 on ~2000 renders) are the slow part of a recipe
    search, and they do not change between recipes or runs."""
    if cache is None:
        return raw_features_of(model, paths, batch_size=32)
    key = hashlib.sha256()
    for p in paths:
        st = Path(p).stat()
        key.update(f"{Path(p).resolve()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    file = cache / f"{backbone}-{len(paths)}-{key.hexdigest()[:16]}.pt"
    if file.is_file():
        return torch.load(file)
    features = raw_features_of(model, paths, batch_size=32)
    with atomic_path(file) as tmp:
        torch.save(features, tmp)
    return features


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", type=Path, nargs="+", help="`hpgs collect` output folders, one per scene")
    ap.add_argument("--garden", type=Path, default=None, help="hpgs-pairs-garden folder (default: ../shared/data)")
    ap.add_argument("--backbones", nargs="*", default=["alexnet", "vgg16", "alexnet+vgg16"], choices=BACKBONES)
    ap.add_argument("--transforms", nargs="*", default=list(FEATURE_TRANSFORMS), choices=FEATURE_TRANSFORMS,
                    help="per-trunk feature transforms")
    ap.add_argument("--l2", type=float, nargs="*", default=[0.1, 0.3, 1.0])
    ap.add_argument("--margins", type=float, nargs="*", default=[0.0, 0.02, 0.05],
                    help="least LPIPS difference of a training pair")
    ap.add_argument("--choose-by", choices=("same-step", "any"), default="same-step",
                    help="held-out pairs that pick the recipe (same-step: as a selector and the garden labels compare)")
    ap.add_argument("--train-pairs", type=int, default=3000, help="oracle pairs per training scene")
    ap.add_argument("--test-pairs", type=int, default=2000, help="oracle pairs per held-out scene, of each kind")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "pref_loso.json")
    ap.add_argument("--write-model", type=Path, default=None)
    ap.add_argument("--write-loso-models", type=Path, default=None, metavar="DIR",
                    help="also write DIR/<scene>.pt: the chosen recipe trained without that scene, for "
                         "`hpgs bench --preference-models DIR` (no benchmark run sees a model that saw its scene)")
    ap.add_argument("--feature-cache", type=Path, default=None,
                    help="keep each backbone's features of the renders here (a second search then takes seconds)")
    ap.add_argument("--no-garden", action="store_true", help="stop after the choice (trial runs); writes no model")
    args = ap.parse_args()
    shared = Path(os.environ.get("HPGS_SHARED", REPO / ".." / "shared"))
    garden = args.garden or shared / "data" / "hpgs-pairs-garden"
    if not (garden / "pairs.csv").is_file():
        raise SystemExit(f"pref_loso: {garden / 'pairs.csv'} not found; pass --garden or set HPGS_SHARED")
    for folder in args.scenes:
        if not (folder / "renders.csv").is_file():
            raise SystemExit(f"pref_loso: {folder / 'renders.csv'} not found; make it with `hpgs collect --out {folder}`")
    torch.set_num_threads(min(4, os.cpu_count() or 1))

    names = [f.name for f in args.scenes]
    renders = {f.name: read_renders(f) for f in args.scenes}
    offset, start = 0, {}
    for name in names:
        start[name] = offset
        offset += len(renders[name])
    paths = [r[0] for name in names for r in renders[name]]
    tests = {kind: {name: oracle_pairs(renders[name], args.test_pairs, same_step=kind == "same-step", seed=1)
                    for name in names} for kind in ("any", "same-step")}
    train = {(name, same, m): oracle_pairs(renders[name], args.train_pairs, same_step=same, seed=0, margin=m)
             for name in names for same in (False, True) for m in args.margins}
    print(f"{len(names)} scenes, {len(paths)} renders: " + ", ".join(f"{n} {len(renders[n])}" for n in names))

    def as_index(pairs_by_scene: Dict[str, List[Tuple[int, int, int]]]) -> Tuple[torch.Tensor, torch.Tensor]:
        rows = [(start[s] + i, start[s] + j, y) for s, ps in pairs_by_scene.items() for i, j, y in ps]
        t = torch.tensor(rows, dtype=torch.long)
        return t[:, :2], t[:, 2]

    trunks = sorted({t for b in args.backbones for t in b.split("+")})
    trunk_features = trunk_features_of(trunks, paths, args.feature_cache)
    results = []
    for backbone, transform in itertools.product(args.backbones, args.transforms):
        model = PreferenceModel(backbone, pretrained=True, feature_transform=transform).eval()
        features = recipe_features(trunk_features, backbone, transform)
        print(f"{backbone}, transform {transform}:")
        for l2, same, margin in itertools.product(args.l2, (False, True), args.margins):
            per_kind: Dict[str, Dict[str, float]] = {"any": {}, "same-step": {}}
            for held in names:
                index, labels = as_index({s: train[(s, same, margin)] for s in names if s != held})
                scores = fit_head_and_score(model, features, index, labels, l2=l2)
                for kind in per_kind:
                    t_index, t_labels = as_index({held: tests[kind][held]})
                    per_kind[kind][held] = pair_accuracy_from_scores(scores, t_index, t_labels)
            recipe = {"backbone": backbone, "feature_transform": transform, "l2": l2,
                      "pairs": "same step" if same else "any two renders", "margin": margin}
            means = {kind: statistics.mean(v.values()) for kind, v in per_kind.items()}
            results.append({**recipe, "loso_mean": means[args.choose_by], "loso_mean_any": means["any"],
                            "loso_mean_same_step": means["same-step"], "per_scene": per_kind[args.choose_by]})
            print(f"  l2 {l2:g}, {recipe['pairs']}, margin {margin:g}: leave-one-scene-out any {means['any']:.3f}, "
                  f"same step {means['same-step']:.3f} ("
                  + ", ".join(f"{s} {a:.3f}" for s, a in per_kind[args.choose_by].items()) + ")")

    best = max(results, key=lambda r: r["loso_mean"])
    recipe_keys = ("backbone", "feature_transform", "l2", "pairs", "margin")
    print(f"chosen by {args.choose_by} pairs among {len(results)} recipes: "
          + ", ".join(f"{k} {best[k]}" for k in recipe_keys) + f" (leave-one-scene-out {best['loso_mean']:.3f})")
    same = best["pairs"] == "same step"
    command = " ".join(["python", "benchmarks/pref_loso.py"] + sys.argv[1:])
    renders_sha = {f.name: hashlib.sha256((f / "renders.csv").read_bytes()).hexdigest() for f in args.scenes}
    recipe = {k: best[k] for k in recipe_keys}
    chosen_features = recipe_features(trunk_features, best["backbone"], best["feature_transform"])
    if args.write_loso_models:
        for held in names:
            model = PreferenceModel(best["backbone"], pretrained=True, feature_transform=best["feature_transform"]).eval()
            index, labels = as_index({s: train[(s, same, best["margin"])] for s in names if s != held})
            fit_head_and_score(model, chosen_features, index, labels, l2=best["l2"])
            others = [n for n in names if n != held]
            model.meta = {
                "training_data": {"oracle_scenes": others, "renders_csv_sha256": [renders_sha[n] for n in others],
                                  "train_pairs": int(len(labels)), "human_labels": "none", "held_out_scene": held},
                "recipe": recipe, "held_out_accuracy": best["per_scene"][held], "backbone_trained": False,
                "made_by": command,
            }
            model.save(args.write_loso_models / f"{held}.pt")
        print(f"wrote {len(names)} models, each without its scene, to {args.write_loso_models}")
    if args.no_garden:
        return
    model = PreferenceModel(best["backbone"], pretrained=True, feature_transform=best["feature_transform"]).eval()
    index, labels = as_index({s: train[(s, same, best["margin"])] for s in names})
    fit_head_and_score(model, chosen_features, index, labels, l2=best["l2"])
    garden_pairs = read_usable_pairs([garden / "pairs.csv"])
    g_images, g_index, g_labels = index_pairs(garden_pairs)
    with torch.no_grad():
        g_raw = recipe_features(trunk_features_of(best["backbone"].split("+"), list(g_images), args.feature_cache),
                                best["backbone"], best["feature_transform"])
        g_scores = model.score_features(model.standardise(g_raw))
    garden_acc = pair_accuracy_from_scores(g_scores, g_index, g_labels)
    constant = float(g_labels.float().mean())
    print(f"garden human labels: {garden_acc:.3f} on {len(garden_pairs)} pairs (constant answer {constant:.3f})")
    record = {
        "recipe": recipe,
        "chosen_by": f"{args.choose_by} held-out pairs",
        "recipes_compared": len(results),
        "oracle": "LPIPS of each render against its photo (higher = worse)",
        "scenes": {n: {"renders": len(renders[n]), "train_pairs_per_policy": args.train_pairs,
                       "test_pairs": {kind: len(tests[kind][n]) for kind in tests}} for n in names},
        "leave_one_scene_out": results,
        "chosen_loso_mean": best["loso_mean"],
        "garden_human_accuracy": garden_acc,
        "garden_pairs": len(garden_pairs),
        "garden_constant_answer": constant,
        "command": command,
    }
    write_text_atomic(args.out, json.dumps(record, indent=1) + "\n")
    print(f"wrote {args.out}")
    if args.write_model:
        model.meta = {
            "training_data": {"oracle_scenes": names, "renders_csv_sha256": [renders_sha[n] for n in names],
                              "train_pairs": int(len(labels)), "human_labels": "none (garden never seen)"},
            "recipe": record["recipe"],
            "leave_one_scene_out_accuracy": best["loso_mean"],
            "garden_human_accuracy": garden_acc,
            "backbone_trained": False,
            "made_by": record["command"],
        }
        model.save(args.write_model)
        print(f"wrote {args.write_model}")


if __name__ == "__main__":
    main()
