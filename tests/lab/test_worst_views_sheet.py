"""benchmarks/worst_views_sheet.py: which runs' worst views go on the sheet."""

from __future__ import annotations

import json
from pathlib import Path

from helpers import load_script

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "worst_views_sheet.py"


def result(path: Path, psnr: float, depth: float, worst: bool = True, cover=None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    view = {"name": "images/0008.jpg", "psnr": psnr, "depth_p10": depth, **({} if cover is None else {"front_cover": cover})}
    data = {"seed": int(path.stem[-1]), "test": {"psnr": psnr + 5}, "test_views": [view],
            "worst_views": [{"name": "images/0008.jpg", "psnr": psnr, "image": f"{path.stem}-worst0.jpg"}] if worst else []}
    path.write_text(json.dumps(data))
    if worst:
        (path.parent / f"{path.stem}-worst0.jpg").write_bytes(b"jpg")


def test_near_keeps_only_worst_views_nearer_than_their_final_sets(tmp_path):
    sheet = load_script(SCRIPT)
    runs = tmp_path / "scene" / "fisherrf" / "random"
    result(runs / "seed0.json", 9.0, 0.1)  # a tenth of its final-set's depth: kept
    result(runs / "final-set" / "seed0.json", 13.0, 1.0, worst=False)
    result(runs / "seed1.json", 11.0, 0.9)  # 0.9x: not near
    result(runs / "final-set" / "seed1.json", 12.0, 1.0, worst=False)
    assert [p.name for _, p in sheet.entries(tmp_path, 0)] == ["seed0-worst0.jpg", "seed1-worst0.jpg"]
    near = sheet.entries(tmp_path, 0, near=0.8)
    assert [p.name for _, p in near] == ["seed0-worst0.jpg"]
    assert "final-set 13.0 dB" in near[0][0] and "depth p10 0.10 (final-set 1.00)" in near[0][0]
    assert "in front cover" not in near[0][0]  # results without the front counts
    # with them, the caption says how much of the image the Gaussians in front cover, here and in the final-set
    result(runs / "seed0.json", 9.0, 0.1, cover=0.62)
    result(runs / "final-set" / "seed0.json", 13.0, 1.0, worst=False, cover=0.05)
    assert "in front cover 62% (5%)" in sheet.entries(tmp_path, 0, near=0.8)[0][0]
