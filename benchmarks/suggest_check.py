"""Do `hpgs suggest`'s poses help? Withhold an arc of a real capture, suggest, take the photos nearest to the
suggestions from the arc, retrain, and compare test PSNR with the same done for `farthest`'s and `random`'s poses.

For each scene (of a suite), seed and block (an arc of the training cameras' azimuths around the capture's
centre, and where the capture has a higher pass, the views above its widest gap in elevation): a base run trains
on every training view but the block; `hpgs suggest` (in-process, on the base run) proposes `--num` poses per
selector (orbit candidates for an arc; sphere candidates for the band, as the orbit's rings stay at the heights of
the photos left); each pose is matched to the nearest photo of the block not yet taken; a run per selector then
trains from scratch on every view but the block plus its matched photos (same seed and steps).
Runs are paired by (scene, block, seed); gains over `farthest` and `random` get the benchmark's intervals
(`hpgs_lab.stats`, the unit being the scene). Results: one JSON per run under OUT, `suggest_check.md`.

    python benchmarks/suggest_check.py --suite real6 --suite-scenes bonsai stitch --data-root .devdata \
        --blocks 3 --seeds 0 --selectors hpgs fisher farthest random --out benchmarks/results/suggest
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import torch

from hpgs_lab import stats
from hpgs_lab.results import Metrics
from hpgs_lab.suites import Scene, load_suite
from hpgs_ns.atomic_write import write_json_atomic, write_text_atomic
from hpgs_ns.dataparser import DATAPARSERS, view_name
from hpgs_ns.ns_train import ns_train_command
from hpgs_ns.suggest import candidates as cand


@dataclass(frozen=True)
class CheckRun:
    """One run of the check (its JSON: OUT/<scene>/block<k>-seed<s>-<selector>.json). `seed` is
    block * 1000 + seed, so that `stats` pairs runs by (scene, block, seed); `selector` "none" is the base run."""

    scene: str
    protocol: str
    selector: str
    seed: int
    block: int
    block_views: int
    test: Metrics
    photos_taken: List[str] = field(default_factory=list)
    withheld: str = "arc"  # the first runs withheld arcs only
    candidates: Optional[str] = None
    config: str = ""
    command: str = ""

    def to_dict(self) -> dict:
        return {**asdict(self), "test": {k: v for k, v in asdict(self.test).items() if v is not None}}

    @classmethod
    def from_dict(cls, data: dict) -> CheckRun:
        return cls(**{**{f.name: data[f.name] for f in fields(cls) if f.name in data}, "test": Metrics.from_dict(data["test"])})


def training_cameras(scene: Scene):
    """(view names, cameras) of the scene's training split, as `ns-train hpgs` reads them."""
    import dataclasses

    import tyro

    default = dataclasses.replace(DATAPARSERS[scene.dataparser], data=scene.path)
    words = [w for k, v in scene.option_dict().items() for w in (f"--{k}", v)]
    config = tyro.cli(type(default), args=words, default=default)
    outputs = config.setup().get_dataparser_outputs("train")
    return [view_name(p, scene.path) for p in outputs.image_filenames], outputs.cameras


def capture_azimuths(cameras) -> torch.Tensor:
    """Each training camera's azimuth (degrees) around the capture's centre and up axis."""
    lay = cand.layout(cameras.camera_to_worlds)
    u = lay.up
    side = torch.tensor([1.0, 0, 0]) if abs(u[0]) < 0.9 else torch.tensor([0, 1.0, 0])
    a = torch.nn.functional.normalize(torch.linalg.cross(u, side, dim=0), dim=0)
    b = torch.linalg.cross(u, a, dim=0)
    rel = cameras.camera_to_worlds[:, :3, 3] - lay.centre
    return torch.rad2deg(torch.atan2(rel @ b, rel @ a)) % 360


def arc_blocks(cameras, blocks: int, arc_deg: float) -> List[List[int]]:
    """Training views in each of `blocks` disjoint arcs (at most `arc_deg` wide) evenly spaced over the azimuths
    the capture covers: all around for an orbit, the covered span for a partial one (a table-top phone capture
    spans ~120 degrees; arcs spread over the full circle would miss it)."""
    azimuth = capture_azimuths(cameras)
    ordered = sorted(azimuth.tolist())
    gaps = [((ordered[(k + 1) % len(ordered)] - z) % 360, k) for k, z in enumerate(ordered)]
    widest, k = max(gaps)
    # The span begins after the widest empty gap; half a photo spacing more at each end, so the first and last
    # photos sit inside it (on a full orbit the span is then the whole circle).
    spacing = sorted(g for g, _ in gaps)[len(gaps) // 2]
    start = ordered[(k + 1) % len(ordered)] - spacing / 2
    span = min(360.0, 360.0 - widest + spacing) if len(ordered) > 1 else 360.0
    step = span / blocks
    width = min(arc_deg, step)
    out = []
    for b in range(blocks):
        low = start + b * step + (step - width) / 2
        out.append([i for i, z in enumerate(azimuth.tolist()) if (z - low) % 360 < width])
    return out


def capture_elevations(cameras) -> torch.Tensor:
    """Each training camera's elevation (degrees) above the plane through the capture's centre, normal to its up."""
    lay = cand.layout(cameras.camera_to_worlds)
    rel = cameras.camera_to_worlds[:, :3, 3] - lay.centre
    height = rel @ lay.up
    return torch.rad2deg(torch.atan2(height, (rel - height[:, None] * lay.up).norm(dim=1)))


def height_band(cameras, min_gap_deg: float, min_views: int) -> List[int]:
    """The training views above the widest gap in elevation (a second, higher pass of the capture), when that gap is
    at least `min_gap_deg` wide and both sides keep `min_views` photos; otherwise none (one continuous band)."""
    elevation = capture_elevations(cameras)
    ordered = sorted(elevation.tolist())
    if len(ordered) < 2 * min_views:
        return []
    gap, k = max((ordered[k + 1] - ordered[k], k) for k in range(min_views - 1, len(ordered) - min_views))
    if gap < min_gap_deg:
        return []
    return [i for i, e in enumerate(elevation.tolist()) if e > ordered[k]]


def nearest_photos(suggested_c2w: Sequence, block_c2w: torch.Tensor, block: Sequence[int]) -> List[int]:
    """For each suggestion in turn, the nearest photo of the block not matched yet (by camera centre)."""
    free = list(block)
    out = []
    for c2w in suggested_c2w:
        if not free:
            break
        centre = torch.tensor(c2w)[:3, 3]
        d = [float((block_c2w[block.index(i)][:3, 3] - centre).norm()) for i in free]
        out.append(free.pop(min(range(len(free)), key=d.__getitem__)))
    return out


def train(scene: Scene, out: Path, name: str, exclude: List[str], seed: int, args) -> dict:
    """One run on every training view but `exclude`; returns its ns-eval metrics."""
    run_root = out / "_runs"
    folder = run_root / scene.name / "hpgs" / name
    cmd = ns_train_command(
        scene.path, run_root, scene.name, name, args.steps,
        trainer={"machine.seed": seed, "final-eval-json": folder / "eval.json"},
        datamanager={"num-initial-views": 100000, "seed": seed, **({"exclude-views": exclude} if exclude else {})},
        selection={"max-rounds": 0},
        model={"rasterizer": args.rasterizer}, extra=shlex.split(args.extra_args),
        dataparser=scene.dataparser, dataparser_options=scene.option_dict(),
    )
    log = out / "_runs" / f"{scene.name}-{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as f:
        if subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode != 0:
            raise SystemExit(f"suggest_check: {name} failed; see {log}")
    return {"test": json.loads((folder / "eval.json").read_text())["results"], "config": str(folder / "config.yml"),
            "command": shlex.join(cmd)}


def check_block(scene: Scene, seed: int, k: int, block: List[int], names: List[str], args,
                withheld_as: str = "arc") -> List[CheckRun]:
    from hpgs_ns.suggest.command import Suggest, load_run, suggest

    out = args.out
    label = f"block{k}-seed{seed}"
    withheld = [names[i] for i in block]
    base = train(scene, out, f"{label}-none", withheld, seed, args)
    run = load_run(Path(base["config"]))
    picks: Dict[str, List[int]] = {}
    candidates = "sphere" if withheld_as == "band" else "orbit"
    for selector in args.selectors:
        answer = suggest(run, Suggest(Path(base["config"]), num=args.num, selector=selector, candidates=candidates,
                                      count=args.count, min_distance=args.min_distance, seed=seed))
        picks[selector] = nearest_photos([s["camera_to_world"] for s in answer["suggestions"]],
                                         run.pipeline.datamanager.train_dataset.cameras.camera_to_worlds[block], block)
    del run

    def final(selector: str) -> CheckRun:
        taken = picks[selector]
        result = train(scene, out, f"{label}-{selector}", [names[i] for i in block if i not in taken], seed, args)
        return CheckRun(scene.name, "withheld-arc", selector, k * 1000 + seed, k, len(block),
                        Metrics.from_dict(result["test"]), [names[i] for i in taken], withheld_as, candidates,
                        result["config"], result["command"])

    with ThreadPoolExecutor(args.parallel) as pool:
        rows = list(pool.map(final, args.selectors))
    rows.append(CheckRun(scene.name, "withheld-arc", "none", k * 1000 + seed, k, len(block),
                         Metrics.from_dict(base["test"]), [], withheld_as, None, base["config"], base["command"]))
    for r in rows:
        write_json_atomic(out / scene.name / f"{label}-{r.selector}.json", r.to_dict())
    return rows


def report(rows: List[CheckRun]) -> str:
    """Gains of each selector's photos over farthest's and random's, paired by (scene, block, seed)."""
    selectors = sorted({r.selector for r in rows} - {"none"})
    pairs: List = []
    for b in ("farthest", "random"):
        pairs += [(s, b) for s in selectors if s != b and b in selectors and (b, s) not in pairs]
    comparisons = stats.compare(rows, "withheld-arc", pairs, metric="psnr", primary=[p for p in pairs if p[1] == "farthest"])
    # What taking any of the arc's photos is worth: a separate family, so it does not dilute the one above.
    gains = stats.compare(rows, "withheld-arc", [(s, "none") for s in selectors], metric="psnr", primary=[])
    cells = sorted({(r.scene, r.block, r.seed) for r in rows})
    psnr = {(r.scene, r.block, r.seed, r.selector): r.test.psnr for r in rows}
    views = {(r.scene, r.block, r.seed): r.block_views for r in rows}
    kind = {(r.scene, r.block, r.seed): r.withheld for r in rows}
    head = ["scene", "withheld", "seed", "photos withheld", "none"] + selectors
    table = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in cells:
        vals = [f"{psnr[c + (s,)]:.2f}" if c + (s,) in psnr else "–" for s in ["none"] + selectors]
        table.append(f"| {c[0]} | {kind[c]} {c[1]} | {c[2] % 1000} | {views[c]} | " + " | ".join(vals) + " |")
    lines = ["Test PSNR after adding the withheld photos nearest to each selector's suggestions (pairs: scene x block "
             "x seed; intervals over scenes).", "", stats.comparison_table(comparisons), "",
             "Gain over adding none of the withheld photos:", "", stats.comparison_table(gains), "",
             "Test PSNR per cell (dB):", "", *table]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="real6")
    ap.add_argument("--suite-scenes", nargs="+", default=[])
    ap.add_argument("--data-root", type=Path, default=Path("../shared/data"))
    ap.add_argument("--blocks", type=int, default=3, help="arcs per scene, evenly spaced in azimuth")
    ap.add_argument("--arc", type=float, default=60.0, help="width of each arc, degrees")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--num", type=int, default=5, help="suggestions (and photos added) per selector")
    ap.add_argument("--count", type=int, default=96, help="orbit candidate poses")
    ap.add_argument("--min-distance", type=float, default=0.5)
    ap.add_argument("--selectors", nargs="+", default=["hpgs", "fisher", "farthest", "random"])
    ap.add_argument("--steps", type=int, default=15000)
    ap.add_argument("--rasterizer", default="auto")
    ap.add_argument("--extra-args", default="")
    ap.add_argument("--parallel", type=int, default=4, help="final runs trained at once")
    ap.add_argument("--band-gap", type=float, default=10.0,
                    help="also withhold the views above the widest gap in elevation when it is at least this wide "
                         "(degrees; a capture with a higher pass); block index --blocks. 0: arcs only")
    ap.add_argument("--only-blocks", type=int, nargs="+", default=None,
                    help="run these blocks only (arcs 0..--blocks-1, the band --blocks): one process per block runs "
                         "the cells side by side")
    ap.add_argument("--report-only", action="store_true", help="rebuild suggest_check.md from the JSONs under --out")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/suggest"))
    args = ap.parse_args()
    if args.report_only:
        rows = [CheckRun.from_dict(json.loads(p.read_text())) for p in sorted(args.out.glob("*/block*-seed*.json"))]
        if not rows:
            raise SystemExit(f"suggest_check: no block*-seed*.json under {args.out}/<scene>/; run the check first")
        text = report(rows)
        write_text_atomic(args.out / "suggest_check.md", text)
        print(text)
        return
    rows = []
    for scene in load_suite(args.suite, args.data_root, args.suite_scenes):
        if scene.smoke:
            continue
        names, cameras = training_cameras(scene)
        blocks = [(block, "arc") for block in arc_blocks(cameras, args.blocks, args.arc)]
        band = height_band(cameras, args.band_gap, args.num) if args.band_gap > 0 else []
        blocks.append((band, "band"))
        if not band:
            print(f"suggest_check: {scene.name} has no separate height band (no gap of {args.band_gap} degrees in "
                  "elevation): arcs only")
        for seed in args.seeds:
            for k, (block, kind) in enumerate(blocks):
                if len(block) < args.num or (args.only_blocks is not None and k not in args.only_blocks):
                    continue
                rows += check_block(scene, seed, k, block, names, args, withheld_as=kind)
    text = report(rows)
    write_text_atomic(args.out / "suggest_check.md", text)
    print(text)
    cells = {(r.scene, r.seed) for r in rows}
    print(f"{len(rows)} runs in {len(cells)} (scene, block, seed) cells -> {args.out}")


if __name__ == "__main__":
    main()
