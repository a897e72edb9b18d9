"""benchmarks/seed_rule.py: the real12 matrix's seed-2 rule reads only seed spreads, and waits for missing pairs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def put(root: Path, scene: str, selector: str, seed: int, psnr: float, protocol: str = "fisherrf") -> None:
    path = root / scene / protocol / selector / f"seed{seed}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"version": 2, "scene": scene, "protocol": protocol, "selector": selector, "seed": seed,
                                "test": {"psnr": psnr, "ssim": 0.5, "lpips": 0.3}, "timing": {"wall_seconds": 1.0,
                                "selection_seconds": 0.0}}))


def rule(out: Path, *args: str) -> tuple:
    done = subprocess.run([sys.executable, str(REPO / "benchmarks" / "seed_rule.py"), "--out", str(out), *args],
                          capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0, done.stderr
    return done.stdout, json.loads((out / "seed_rule.json").read_text())


def test_a_scene_gets_seed_2_from_its_widest_selector_spread_and_waits_only_while_it_could_still(tmp_path):
    # wide: random's seeds differ by 1.5 dB (a gain would not matter: hpgs's large lead is not read)
    put(tmp_path, "wide", "random", 0, 20.0), put(tmp_path, "wide", "random", 1, 21.5)
    put(tmp_path, "wide", "hpgs", 0, 25.0), put(tmp_path, "wide", "hpgs", 1, 25.2)
    # narrow: every spread under 1 dB, but blend has only seed 0: undecided until its pair is in
    put(tmp_path, "narrow", "random", 0, 20.0), put(tmp_path, "narrow", "random", 1, 20.9)
    put(tmp_path, "narrow", "hpgs", 0, 20.0), put(tmp_path, "narrow", "hpgs", 1, 19.6)
    put(tmp_path, "narrow", "blend", 0, 20.0)
    put(tmp_path, "narrow", "random", 2, 30.0)  # a seed 2 already there is not part of the rule
    put(tmp_path, "other", "random", 0, 10.0, protocol="hpgs"), put(tmp_path, "other", "random", 1, 15.0, protocol="hpgs")
    out, figures = rule(tmp_path, "--selectors", "random", "hpgs", "blend")
    assert figures["seed_2"] == ["wide"] and figures["not_decided"] == ["narrow"]
    assert abs(figures["scenes"]["wide"]["d"] - 1.5) < 1e-9 and abs(figures["scenes"]["narrow"]["d"] - 0.9) < 1e-9
    assert figures["scenes"]["narrow"]["missing"] == ["blend"] and "other" not in figures["scenes"]
    assert "wide: d = 1.50 dB (random) -> seed 2" in out and "narrow: d = 0.90 dB (random) -> not decided yet (blend" in out
    # once blend's seed 1 is in (0.5 dB away), narrow stays at two seeds
    put(tmp_path, "narrow", "blend", 1, 20.5)
    out, figures = rule(tmp_path, "--selectors", "random", "hpgs", "blend", "--threshold", "1.0")
    assert figures["seed_2"] == ["wide"] and figures["not_decided"] == [] and "narrow: d = 0.90 dB (random) -> seeds 0-1" in out
