"""The real12 matrix's seed-2 rule (docs/lab/real12-matrix-plan.md), read from a results folder: for each scene, d =
the largest |seed 0 - seed 1| difference of a selector's run PSNR; a scene with d above the threshold (1.0 dB) gets
seed 2 for every selector. The rule reads only spreads between seeds, never a gain, so it is applied before any
comparison is read. Prints a line per scene and the `--suite-scenes` list, and writes JSON.

    python benchmarks/seed_rule.py --out benchmarks/results/real12 [--protocol fisherrf] [--threshold 1.0] \
        [--selectors random farthest fisher hpgs blend] [--json benchmarks/results/real12/seed_rule.json]

A scene where a listed selector lacks seed 0 or 1 is named as not decidable yet (the rule waits for its pair).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from hpgs_lab.results import RunResult, load_results
from hpgs_ns.atomic_write import write_json_atomic


def seed_spreads(rows: Sequence[RunResult], protocol: str, selectors: Optional[Sequence[str]] = None) -> Dict[str, dict]:
    """scene -> {"d": largest |seed0 - seed1| run PSNR over the selectors with both seeds, "by_selector":
    {selector: |difference|}, "missing": [listed selectors without both seeds]}. With selectors missing, `d` is a lower
    bound of the scene's d (`seed_two_scenes` decides on it only when it already passes the threshold)."""
    psnr: Dict[str, Dict[str, Dict[int, float]]] = {}
    for r in rows:
        if r.protocol != protocol or r.repeat or r.smoke or r.is_reference or r.seed not in (0, 1):
            continue
        psnr.setdefault(r.scene, {}).setdefault(r.selector, {})[r.seed] = r.test.psnr
    out = {}
    for scene, by_sel in sorted(psnr.items()):
        wanted = list(selectors) if selectors else sorted(by_sel)
        diffs = {s: abs(by_sel[s][0] - by_sel[s][1]) for s in wanted if s in by_sel and {0, 1} <= set(by_sel[s])}
        missing = [s for s in wanted if s not in diffs]
        out[scene] = {"d": max(diffs.values()) if diffs else None, "by_selector": diffs, "missing": missing}
    return out


def decision(spread: dict, threshold: float) -> Optional[bool]:
    """Whether the scene gets seed 2: True when d passes `threshold` (whatever the missing selectors would show),
    False when every listed selector has both seeds and none passes it, None while it waits for missing ones."""
    if spread["d"] is not None and spread["d"] > threshold:
        return True
    return None if spread["missing"] else False


def seed_two_scenes(spreads: Dict[str, dict], threshold: float) -> List[str]:
    """The scenes the rule gives seed 2."""
    return [s for s, v in spreads.items() if decision(v, threshold)]


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="a results folder (<scene>/<protocol>/<selector>/seed*.json)")
    parser.add_argument("--protocol", default="fisherrf")
    parser.add_argument("--threshold", type=float, default=1.0, help="dB; the plan's 1.0")
    parser.add_argument("--selectors", nargs="*", default=None, help="the selectors the rule reads (default: all present)")
    parser.add_argument("--json", type=Path, default=None, help="where to write the figures (default: OUT/seed_rule.json)")
    args = parser.parse_args(argv)
    spreads = seed_spreads(load_results(args.out), args.protocol, args.selectors)
    if not spreads:
        raise SystemExit(f"seed_rule: no {args.protocol} runs of seeds 0 and 1 under {args.out}")
    for scene, v in spreads.items():
        shown = f"d = {v['d']:.2f} dB ({max(v['by_selector'], key=v['by_selector'].get)})" if v["d"] is not None else "no pair yet"
        verdict = {True: "seed 2", False: "seeds 0-1",
                   None: f"not decided yet ({', '.join(v['missing'])} without seeds 0 and 1)"}[decision(v, args.threshold)]
        print(f"{scene}: {shown} -> {verdict}")
    chosen = seed_two_scenes(spreads, args.threshold)
    waiting = [s for s, v in spreads.items() if decision(v, args.threshold) is None]
    print(f"seed 2: --suite-scenes {' '.join(chosen)}" if chosen else "seed 2: no scene yet")
    if waiting:
        print(f"not decided yet: {' '.join(waiting)}")
    write_json_atomic(args.json or args.out / "seed_rule.json",
                      {"protocol": args.protocol, "threshold": args.threshold, "selectors": args.selectors,
                       "scenes": spreads, "seed_2": chosen, "not_decided": waiting})


if __name__ == "__main__":
    main()
