"""How well each selector's scores find the candidates the splat renders worst, from `--log-candidate-scores` logs.

Reads every `*-candidates.jsonl.gz` (or `.jsonl`) under a results folder (`hpgs bench --log-candidate-scores`):
per round, each built-in selector's score of every candidate and the candidate's render error against its withheld
photo (the oracle). For each selector: the Spearman correlation of its scores with the oracle LPIPS (mean over
rounds) and the oracle percentile of its top pick (1.0: it picked the worst-rendered candidate). Then a linear
combination of the selectors' per-round z-scores, fitted to the oracle's z-scores by least squares *leaving one
scene out*: the numbers reported for it are on the scene it never saw.

    python benchmarks/candidate_scores.py benchmarks/results/suite --out candidate_scores.json

Is the oracle the right target? Where a logged run has its test PSNR at every round step and an `initial`
reference (`hpgs_lab.gain_fit.view_gains`), each round's chosen view is set against what that round gained in
test PSNR (over the reference): the Spearman correlation of the pick's render-error percentile with the gain.

`--selectors farthest hpgs` restricts the combination to those scores and prints its weights fitted on every
scene: the `blend` selector's defaults (hpgs_ns/selectors/blend.py) come from that line. `--subsets` also judges
every subset of the logged scores leave one scene out.
"""

from __future__ import annotations

import argparse
import gzip
import itertools
import json
import re
from pathlib import Path
from typing import Dict, List

import numpy as np
from scipy.stats import spearmanr


def load_rounds(folder: Path) -> List[dict]:
    rounds = []
    paths = sorted(folder.glob("*/*/*/*-candidates.jsonl.gz")) + sorted(folder.glob("*/*/*/*-candidates.jsonl"))
    for path in paths:
        scene = path.relative_to(folder).parts[0]
        stem = path.name.split("-candidates.jsonl")[0]  # seed<k> or seed<k>-repeat<r>, as its result is named
        match = re.fullmatch(r"seed(\d+)(?:-repeat(\d+))?", stem)
        done = match is not None and path.with_name(stem + ".json").is_file()  # a run killed mid-way has no result
        which = {"scene": scene, "seed": int(match[1]) if done else None, "repeat": int(match[2] or 0) if done else 0}
        text = gzip.decompress(path.read_bytes()).decode() if path.suffix == ".gz" else path.read_text()
        for line in text.splitlines():
            if line.strip():
                rounds.append({**json.loads(line), **which})
    return rounds


def oracle_vs_gain(rounds: List[dict], folder: Path) -> Dict[str, object]:
    """Spearman, over rounds, of the chosen view's render-error percentile with the round's test-PSNR gain."""
    from hpgs_lab.gain_fit import view_gains
    from hpgs_lab.results import load_results

    gains = {}
    for v in view_gains(load_results(folder)):
        steps = [p.step for p in v.run.psnr_per_round]
        key = (v.scene, v.selector, v.run.seed, v.run.repeat)
        for k, step in enumerate(steps[: len(v.G) - 1]):
            gains[key + (step,)] = v.G[k + 1] - v.G[k]
    pairs: Dict[str, List] = {}
    for r in rounds:
        gain = gains.get((r["scene"], r["selector"], r["seed"], r["repeat"], r["step"]))
        if gain is None or not r["chosen"]:
            continue
        chosen = error_percentile(np.array(r["oracle"]["lpips"]), r["candidates"].index(r["chosen"][0]))
        pairs.setdefault(r["scene"], []).append((chosen, gain))
    every = [p for ps in pairs.values() for p in ps]
    if len(every) < 3:
        return {}
    rho = lambda ps: float(spearmanr([a for a, _ in ps], [b for _, b in ps]).statistic)  # noqa: E731
    return {"rounds": len(every), "spearman": rho(every), "per_scene": {s: rho(ps) for s, ps in pairs.items()}}


def zscore(x: np.ndarray) -> np.ndarray:
    sd = x.std()
    return (x - x.mean()) / sd if sd > 0 else np.zeros_like(x)


def error_percentile(oracle: np.ndarray, index: int) -> float:
    """Share of the round's candidates rendered better than candidate `index` (1.0: it is the worst rendered)."""
    return float((oracle < oracle[index]).mean())


def quality(scores: np.ndarray, oracle: np.ndarray) -> Dict[str, float]:
    """Spearman with the oracle error and the oracle percentile of the top-scored candidate."""
    rho = spearmanr(scores, oracle).statistic if len(scores) > 2 and scores.std() > 0 else float("nan")
    return {"spearman": float(rho), "top_percentile": error_percentile(oracle, int(np.argmax(scores)))}


def summarize(rounds: List[dict], selectors: List[str]) -> Dict[str, Dict[str, float]]:
    out = {}
    for sel in selectors:
        q = [quality(np.array(r["scores"][sel]), np.array(r["oracle"]["lpips"])) for r in rounds]
        out[sel] = {k: float(np.nanmean([x[k] for x in q])) for k in ("spearman", "top_percentile")}
    return out


def design(rounds: List[dict], selectors: List[str]):
    """Per round: the selectors' z-scored scores [candidates, selectors] and the oracle LPIPS z-scored."""
    x = [np.stack([zscore(np.nan_to_num(np.array(r["scores"][s]))) for s in selectors], 1) for r in rounds]
    y = [zscore(np.array(r["oracle"]["lpips"])) for r in rounds]
    return x, y


def fit_weights(rounds: List[dict], selectors: List[str]) -> np.ndarray:
    """Least squares of the oracle's z-scores on the selectors' z-scores, pooled over rounds."""
    xs, ys = design(rounds, selectors)
    w, *_ = np.linalg.lstsq(np.concatenate(xs), np.concatenate(ys), rcond=None)
    return w


def leave_one_scene_out(rounds: List[dict], selectors: List[str]) -> Dict[str, object]:
    """Weights fitted on the other scenes, judged on each held-out scene; mean over scenes."""
    scenes = sorted({r["scene"] for r in rounds})
    if len(scenes) < 2:
        return {}
    per_scene, weights = {}, {}
    for held in scenes:
        w = fit_weights([r for r in rounds if r["scene"] != held], selectors)
        test = [r for r in rounds if r["scene"] == held]
        q = [quality(x @ w, np.array(r["oracle"]["lpips"])) for x, r in zip(design(test, selectors)[0], test)]
        per_scene[held] = {k: float(np.nanmean([v[k] for v in q])) for k in ("spearman", "top_percentile")}
        weights[held] = dict(zip(selectors, map(float, w)))
    mean = {k: float(np.mean([v[k] for v in per_scene.values()])) for k in ("spearman", "top_percentile")}
    return {"held_out_mean": mean, "per_scene": per_scene, "weights": weights}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--selectors", nargs="+", default=None, help="combine only these scores (default: all logged)")
    ap.add_argument("--subsets", action="store_true", help="also judge every subset of the logged scores")
    args = ap.parse_args()
    rounds = load_rounds(args.folder)
    if not rounds:
        raise SystemExit(f"candidate_scores: no *-candidates.jsonl.gz under {args.folder}; run hpgs bench --log-candidate-scores")
    logged = sorted(rounds[0]["scores"])
    selectors = args.selectors or logged
    unknown = sorted(set(selectors) - set(logged))
    if unknown:
        raise SystemExit(f"candidate_scores: {', '.join(unknown)} not in the logs (logged: {', '.join(logged)})")
    result = {"rounds": len(rounds), "scenes": sorted({r["scene"] for r in rounds}),
              "per_selector": summarize(rounds, logged), "combined": selectors,
              "combination_loso": leave_one_scene_out(rounds, selectors),
              "weights_all_scenes": dict(zip(selectors, map(float, fit_weights(rounds, selectors))))}
    result["oracle_vs_gain"] = oracle_vs_gain(rounds, args.folder)
    if args.subsets:
        result["subsets_loso"] = {"+".join(sub): leave_one_scene_out(rounds, list(sub))["held_out_mean"]
                                  for k in range(1, len(logged) + 1) for sub in itertools.combinations(logged, k)}
    print(f"{len(rounds)} rounds, scenes {', '.join(result['scenes'])}")
    print("| scores | Spearman with oracle LPIPS | top pick's oracle percentile |\n|---|---|---|")
    for sel, q in result["per_selector"].items():
        print(f"| {sel} | {q['spearman']:.3f} | {q['top_percentile']:.3f} |")
    if result["combination_loso"]:
        q = result["combination_loso"]["held_out_mean"]
        print(f"| {' + '.join(selectors)} combined (leave one scene out) | {q['spearman']:.3f} | {q['top_percentile']:.3f} |")
    for name, q in result.get("subsets_loso", {}).items():
        print(f"| subset {name} (leave one scene out) | {q['spearman']:.3f} | {q['top_percentile']:.3f} |")
    if result["oracle_vs_gain"]:
        q = result["oracle_vs_gain"]
        print(f"chosen view's render-error percentile vs the round's test-PSNR gain: Spearman {q['spearman']:.3f} over "
              f"{q['rounds']} rounds (" + ", ".join(f"{s} {v:.2f}" for s, v in q["per_scene"].items()) + ")")
    print("weights fitted on every scene: " + ", ".join(f"{k} {v:.3f}" for k, v in result["weights_all_scenes"].items()))
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
