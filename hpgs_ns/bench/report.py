"""`hpgs bench`'s report: the results table, paired comparisons, noise and throughput, plots, stress tables.

Everything here reads the per-run JSON (`load_results`) and writes nothing but tables and figures, so
`hpgs bench --report-only` can rebuild it from any results folder (`write_report`). Which selector beats which
is decided in `paired.md` only (`stats`: runs paired by scene and seed, intervals over scenes); `table.md`'s
means and spreads are for reading.
"""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from hpgs_ns.atomic_write import atomic_path, write_text_atomic
from hpgs_ns.bench import stats
from hpgs_ns.bench.protocols import REFERENCES, row_order

METRICS = ("psnr", "ssim", "lpips")
BASELINE = "random"


def work_table(rows: List[dict]) -> str:
    """What selection computed and what it skipped, per selector (mean over runs): renders at the size the
    selector needs vs the dataset's, Fisher's frustum-culled (view, Gaussian) pairs vs all of them."""
    groups: Dict[Tuple[str, str, str], List[dict]] = {}
    for r in rows:
        if r.get("selection_work"):
            groups.setdefault((r["scene"], r["protocol"], r["selector"]), []).append(r)
    if not groups:
        return ""
    lines = [
        "| scene | protocol | selector | views rendered | pixels vs full size | pairs vs unculled | backward passes | forwards | selection (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def mean(group: List[dict], key: str) -> float:
        return sum(g["selection_work"].get(key, 0.0) for g in group) / len(group)

    for (scene, protocol, sel), group in sorted(groups.items()):
        full, pairs_all = mean(group, "pixels_full_resolution"), mean(group, "pairs_unculled")
        pixels = f"{100 * mean(group, 'pixels_rendered') / full:.0f}%" if full else "-"
        pairs = f"{100 * mean(group, 'pairs_differentiated') / pairs_all:.0f}%" if pairs_all else "-"
        seconds = sum(g["selection_seconds"] for g in group) / len(group)
        lines.append(
            f"| {scene} | {protocol} | {sel} | {mean(group, 'views_rendered'):.0f} | {pixels} | {pairs} | "
            f"{mean(group, 'backward_passes'):.0f} | {mean(group, 'model_forwards'):.0f} | {seconds:.1f} |"
        )
    return "\n".join(lines) + "\n"


def load_results(out: Path) -> List[dict]:
    return [json.loads(p.read_text()) for p in sorted(out.glob("*/*/*/seed*.json"))]


def _mean_std(values: Sequence[float]) -> Tuple[float, float]:
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else 0.0
    return mean, std


def save_figure(fig, path: Path, rect=(0, 0, 1, 1)) -> Path:
    """Lay out, write (temp file, then rename) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout(rect=rect)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return Path(path)


def _timed(row: dict) -> bool:
    """Whether a run recorded when it ran, and on which machine (its sweep id)."""
    return bool(row.get("sweep_id") and row.get("started_at") is not None and row.get("wall_seconds"))


def _machine(row: dict) -> Tuple[str, str]:
    """(device, host of the sweep): runs of two sweeps on one machine share its GPU."""
    return short_device(row), str(row["sweep_id"]).rsplit("-", 1)[0]


def solo(row: dict, rows: Sequence[dict] = ()) -> bool:
    """Whether a run had its GPU to itself (its wall and per-step times then mean what they say): one run per GPU,
    and no run among `rows` on the same machine overlapping it in time (two sweeps can share one GPU)."""
    if int(row.get("runs_per_gpu", 1)) != 1:
        return False
    if not _timed(row):
        return True
    start, end = row["started_at"], row["started_at"] + row["wall_seconds"]
    return not any(r is not row and _timed(r) and _machine(r) == _machine(row)
                   and r["started_at"] < end and start < r["started_at"] + r["wall_seconds"] for r in rows)


def markdown_table(rows: List[dict]) -> str:
    """Mean +- std over seeds per (scene, protocol, selector); times from solo runs only (one run per GPU and no
    other sweep's run beside it; "–" when every run of the row shared its GPU). Repeats (`--repeats`) are left out."""
    groups: Dict[Tuple[str, str, str], List[dict]] = {}
    for r in rows:
        if not r.get("repeat"):
            groups.setdefault((r["scene"], r["protocol"], r["selector"]), []).append(r)
    lines = [
        "| scene | protocol | selector | seeds | views | PSNR | SSIM | LPIPS | devices | wall (s, solo) | selection (s, solo) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    order = {name: i for i, name in enumerate(row_order())}
    for (scene, protocol, sel), group in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], order.get(kv[0][2], 99))):
        cells = []
        for key in ("psnr", "ssim", "lpips"):
            m, s = _mean_std([g["test"][key] for g in group])
            digits = 2 if key == "psnr" else 3
            # One seed has no spread to show (a "± 0.00" would read as a measured one).
            cells.append(f"{m:.{digits}f} ± {s:.{digits}f}" if len(group) > 1 else f"{m:.{digits}f}")
        alone = [g for g in group if solo(g, rows)]
        wall = f"{_mean_std([g['wall_seconds'] for g in alone])[0]:.0f}" if alone else "–"
        selt = f"{_mean_std([g['selection_seconds'] for g in alone])[0]:.1f}" if alone else "–"
        views = group[0]["num_views_final"]
        devices = device_counts(group)
        lines.append(
            f"| {scene} | {protocol} | {sel} | {len(group)} | {views} | {' | '.join(cells)} | {devices} | {wall} | {selt} |"
        )
    return "\n".join(lines) + "\n"


def short_device(row: dict) -> str:
    """`NVIDIA H100 80GB HBM3` -> `H100`, `cpu x2` -> `cpu`."""
    return str(row.get("device", "?")).replace("NVIDIA ", "").split()[0]


def device_counts(group: List[dict]) -> str:
    """`H100 x2, H200`: wall times are only comparable on one device, and sweeps span sessions and machines."""
    counts: Dict[str, int] = {}
    for g in group:
        counts[short_device(g)] = counts.get(short_device(g), 0) + 1
    return ", ".join(name if n == 1 else f"{name} x{n}" for name, n in sorted(counts.items()))


def make_plots(rows: List[dict], out: Path) -> List[Path]:
    """PSNR vs wall time per selector, and PSNR at each selection round's step, per (scene, protocol)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    keys = sorted({(r["scene"], r["protocol"]) for r in rows})
    for scene, protocol in keys:
        group = [r for r in rows if r["scene"] == scene and r["protocol"] == protocol]
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
        # One marker per device: run times are only comparable on one device.
        markers = dict(zip(sorted({short_device(r) for r in group}), "o^sDvP"))
        for i, sel in enumerate(sorted({r["selector"] for r in group})):
            rs = [r for r in group if r["selector"] == sel]
            for n, r in enumerate(rs):
                ax1.scatter(r["wall_seconds"], r["test"]["psnr"], s=30, color=f"C{i}",
                            marker=markers[short_device(r)], label=sel if n == 0 else None)
            if sel in REFERENCES:
                continue
            for k, r in enumerate(rs):
                # Against the step, not the view count: early rounds' PSNR is mostly training progress, and a
                # views axis read it as the views' doing.
                pts = [(p["step"], p["test_psnr"]) for p in r["psnr_per_round"] if p["test_psnr"] is not None]
                if "steps" in r:
                    pts.append((r["steps"], r["test"]["psnr"]))
                if not pts:
                    continue
                ax2.plot(*zip(*pts), marker="o", ms=3, color=f"C{i}",
                         label=sel if k == 0 else None, alpha=0.8)
        ax1.set(xlabel="wall time (s)", ylabel="test PSNR (dB)", title=f"{scene} / {protocol}: PSNR vs run time")
        ax2.set(xlabel="training step (a view is added at each round's point)", ylabel="test PSNR (dB)",
                title="PSNR at each selection round")
        handles, labels = ax1.get_legend_handles_labels()
        if len(markers) > 1:
            for device, marker in markers.items():
                handles.append(ax1.scatter([], [], marker=marker, color="grey", s=30))
                labels.append(device)
        ax1.legend(handles, labels, fontsize=8)
        ax2.legend(fontsize=8)
        path = save_figure(fig, out / f"{scene}-{protocol}.png")
        paths.append(path)
        map_path = camera_map(group, out / f"{scene}-{protocol}-cameras.png")
        if map_path is not None:
            paths.append(map_path)
    return paths


def camera_centres(scene: Path) -> Optional[Dict[str, Tuple[float, float]]]:
    """Top-down 2D positions of a scene's cameras by view name (for COLMAP scenes by COLMAP's image name, the
    view name without its image folder): camera centres (COLMAP model, or transforms.json) projected on the plane
    of their two principal directions (the capture's ground plane for orbit-like captures)."""
    import numpy as np

    from hpgs_ns.dataparser import view_name
    from hpgs_ns.scenes.colmap_model import camera_pose, read_images

    scene = Path(scene)
    images = read_images(scene / "sparse" / "0")
    if images is not None:
        names = [im.name for im in images.values()]
        centres = np.stack([camera_pose(im)[1] for im in images.values()])
    elif (scene / "transforms.json").is_file():
        frames = json.loads((scene / "transforms.json").read_text())["frames"]
        names = [view_name(scene / f["file_path"], scene) for f in frames]
        centres = np.array([[row[3] for row in f["transform_matrix"][:3]] for f in frames], dtype=float)
    else:
        return None
    centred = centres - centres.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    xy = centred @ vt[:2].T
    return {n: (float(x), float(y)) for n, (x, y) in zip(names, xy)}


def camera_map(group: List[dict], path: Path) -> Optional[Path]:
    """One panel per selector (first seed): all cameras, the initial views, and the chosen ones numbered."""
    import matplotlib.pyplot as plt

    runs = [r for r in sorted(group, key=lambda r: r["seed"]) if r["selector"] not in REFERENCES and r["chosen_views"]]
    if not runs:
        return None
    data = shlex.split(runs[0]["command"])
    scene = Path(data[data.index("--data") + 1]) if "--data" in data else None
    pos = camera_centres(scene) if scene is not None and scene.is_dir() else None
    if not pos:
        return None
    first = {}
    for r in runs:
        first.setdefault(r["selector"], r)

    def at(name: str) -> Optional[Tuple[float, float]]:
        # a view name, a COLMAP image name (the view name without its image folder), or a 0.1 bare file name
        return pos.get(name) or pos.get(Path(*Path(name).parts[1:]).as_posix() if len(Path(name).parts) > 1 else name)

    fig, axes = plt.subplots(1, len(first), figsize=(3.6 * len(first), 3.6), squeeze=False)
    all_xy = list(pos.values())
    for ax, (sel, r) in zip(axes[0], sorted(first.items())):
        ax.scatter(*zip(*all_xy), s=6, c="lightgrey", label="withheld / test")
        initial = [xy for xy in map(at, r["initial_views"]) if xy is not None]
        if initial:
            ax.scatter(*zip(*initial), s=12, c="C0", label="initial")
        chosen = [(k, at(name)) for k, name in enumerate(r["chosen_views"], 1) if at(name) is not None]
        if chosen:
            ax.scatter(*zip(*[xy for _, xy in chosen]), s=30, c="C3", label="added (in order)")
        for k, xy in chosen:
            ax.annotate(str(k), xy, fontsize=8, xytext=(3, 3), textcoords="offset points")
        ax.set(title=f"{sel} (seed {r['seed']})", xticks=[], yticks=[], aspect="equal")
    # Below the panels: inside one it would hide cameras.
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="lower center", ncol=3, fontsize=8, frameon=False)
    save_figure(fig, path, rect=(0, 0.07, 1, 1))
    return path


# ------------------------------------------------------------------------------------------------------------
# Stress mode: how much each selector loses on perturbed copies (`hpgs bench --stress`)


def split_scene_name(scene: str) -> Tuple[str, str]:
    """`"ring+exposure"` -> `("ring", "exposure")`; a clean scene's perturbation is `"clean"`."""
    base, _, perturbation = scene.partition("+")
    return base, perturbation or "clean"


Key = Tuple[str, str, str, str]  # (base scene, protocol, selector, perturbation)


def _psnr_by_seed(rows: List[dict]) -> Dict[Key, Dict[int, float]]:
    """(base scene, protocol, selector, perturbation) -> {seed: test PSNR}."""
    values: Dict[Key, Dict[int, float]] = {}
    for r in rows:
        base, perturbation = split_scene_name(r["scene"])
        values.setdefault((base, r["protocol"], r["selector"], perturbation), {})[r["seed"]] = r["test"]["psnr"]
    return values


def _mean(values) -> float:
    values = list(values)
    return sum(values) / len(values)


def _paired_change(psnr: Dict[Key, Dict[int, float]], key: Key) -> Optional[float]:
    """Mean over seeds of (perturbed - clean), on the seeds run both ways: seeds differ in their initial views,
    so a perturbed seed is only compared with the same seed's clean run. None without a common seed."""
    clean = psnr.get(key[:3] + ("clean",), {})
    seeds = sorted(set(psnr.get(key, {})) & set(clean))
    return _mean(psnr[key][s] - clean[s] for s in seeds) if seeds else None


def _stress_groups(psnr: Dict[Key, Dict[int, float]]):
    """(base, protocol, perturbations, selectors in bench order) for every group with a perturbed run."""
    order = {name: i for i, name in enumerate(row_order())}
    for base, protocol in sorted({k[:2] for k in psnr if k[3] != "clean"}):
        keys = [k for k in psnr if k[:2] == (base, protocol)]
        perturbations = sorted({k[3] for k in keys if k[3] != "clean"})
        selectors = sorted({k[2] for k in keys}, key=lambda s: (order.get(s, 99), s))
        yield base, protocol, perturbations, selectors


def stress_plot(rows: List[dict], out: Path) -> List[Path]:
    """Per (scene, protocol): bars of the PSNR change from clean (paired by seed), one group per selector, one bar
    per perturbation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    psnr = _psnr_by_seed(rows)
    paths = []
    for base, protocol, perturbations, selectors in _stress_groups(psnr):
        selectors = [s for s in selectors if any(_paired_change(psnr, (base, protocol, s, p)) is not None for p in perturbations)]
        if not selectors:
            continue
        fig, ax = plt.subplots(figsize=(1.4 * len(selectors) + 2, 3.6))
        width = 0.8 / len(perturbations)
        for j, p in enumerate(perturbations):
            xs = [i + (j - (len(perturbations) - 1) / 2) * width for i in range(len(selectors))]
            drops = [_paired_change(psnr, (base, protocol, s, p)) for s in selectors]
            ax.bar(xs, [float("nan") if d is None else d for d in drops], width, label=p)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xticks(range(len(selectors)), selectors)
        ax.set(ylabel="test PSNR change from clean (dB)", title=f"{base} / {protocol}: stress (same seeds)")
        ax.legend(fontsize=8)
        path = save_figure(fig, out / f"{base}-{protocol}-stress.png")
        paths.append(path)
    return paths


def stress_table(rows: List[dict]) -> str:
    """Per scene and protocol with perturbed runs: test PSNR per selector, clean and under each perturbation, with
    the change from clean in dB paired by seed; "" when no row is from a perturbed scene."""
    psnr = _psnr_by_seed(rows)
    lines = []
    for base, protocol, perturbations, selectors in _stress_groups(psnr):
        lines += [
            f"**{base} / {protocol}**: test PSNR (dB), mean over seeds; clean over the seeds also run perturbed; "
            "in brackets the change from clean on the same seeds",
            "",
            "| selector | clean | " + " | ".join(perturbations) + " | mean change |",
            "|---|---|" + "---|" * len(perturbations) + "---|",
        ]
        for sel in selectors:
            clean = psnr.get((base, protocol, sel, "clean"), {})
            stressed_seeds = set().union(*(psnr.get((base, protocol, sel, p), {}) for p in perturbations)) & set(clean)
            clean_cell = f"{_mean(clean[s] for s in sorted(stressed_seeds or clean)):.2f}" if clean else "–"
            cells, drops = [], []
            for p in perturbations:
                runs = psnr.get((base, protocol, sel, p))
                if not runs:
                    cells.append("–")
                    continue
                change = _paired_change(psnr, (base, protocol, sel, p))
                drops.append(change)
                mean = _mean(runs.values())
                cells.append(f"{mean:.2f}" if change is None else f"{mean:.2f} ({change:+.2f})")
            # Averaged only over a full row: a mean of some perturbations is not comparable with one of all.
            full = len(drops) == len(perturbations) and None not in drops
            avg = f"{_mean(drops):+.2f}" if full else "–"
            lines.append(f"| {sel} | {clean_cell} | {' | '.join(cells)} | {avg} |")
        lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------------------
# Paired comparisons (which selector to use), noise, throughput


def comparable(rows: List[dict]) -> List[dict]:
    """The rows comparisons are made from: first repeats only, no smoke-check scenes, no stress copies."""
    return [r for r in rows if not r.get("repeat") and not r.get("smoke") and "+" not in r["scene"]]


def comparison_plan(rows: List[dict], protocol: str, default: str = "hpgs") -> Tuple[List[Tuple[str, str]], List[Tuple[str, str]]]:
    """(primary, other) comparisons of one protocol, fixed before looking at any gain: each selector against
    `random`, and the default selector against the other selector with the highest mean PSNR over scenes; every
    other pair of selectors is secondary (Holm-adjusted)."""
    order = {name: i for i, name in enumerate(row_order())}
    selectors = sorted({r["selector"] for r in rows if r["protocol"] == protocol and r["selector"] not in REFERENCES},
                       key=lambda s: (order.get(s, 99), s))
    primary = [(s, BASELINE) for s in selectors if s != BASELINE and BASELINE in selectors]
    others = [s for s in selectors if s not in (default, BASELINE)]
    if default in selectors and others:
        def scene_mean(sel: str) -> float:
            by_scene: Dict[str, List[float]] = {}
            for r in rows:
                if r["protocol"] == protocol and r["selector"] == sel:
                    by_scene.setdefault(r["scene"], []).append(r["test"]["psnr"])
            return sum(sum(v) / len(v) for v in by_scene.values()) / max(len(by_scene), 1)

        primary.append((default, max(others, key=scene_mean)))
    secondary = [(a, b) for i, a in enumerate(selectors) for b in selectors[i + 1:]
                 if (a, b) not in primary and (b, a) not in primary]
    return primary, secondary


def paired_report(rows: List[dict]) -> str:
    """Per protocol: the scenes (training and test views), the paired gain over random per scene, and the
    comparisons with their 95% intervals and verdicts, for PSNR, SSIM and LPIPS."""
    rows = comparable(rows)
    out: List[str] = []
    for protocol in sorted({r["protocol"] for r in rows}):
        group = [r for r in rows if r["protocol"] == protocol]
        primary, secondary = comparison_plan(group, protocol)
        if not primary and not secondary:
            continue
        out += [f"#### {protocol} protocol", "", scenes_table(group), ""]
        if not primary:  # run without `random`: no gain over it to report, every pair Holm-adjusted
            out += ["No `random` runs in this protocol: every comparison is Holm-adjusted.", ""]
        # The code hash covers each selector's own files, so it is counted per selector
        versions = max(len({(r.get("settings") or {}).get("code") for r in group if r["selector"] == sel} - {None})
                       for sel in {r["selector"] for r in group})
        if versions > 1:
            out += [f"A selector's runs here were made by up to {versions} versions of the code (`--accept-code-change`).", ""]
        for sel, _ in [p for p in primary if p[1] == BASELINE]:
            gains = stats.paired_gains(group, sel, BASELINE, protocol, "psnr")
            out += [f"PSNR gain of `{sel}` over `random`, per scene (seeds paired):", "",
                    stats.scene_table(stats.scene_summaries(gains), "psnr"), ""]
        sentences = []
        for metric in METRICS:
            comparisons = stats.compare(group, protocol, primary + secondary, metric=metric, primary=primary)
            out += [f"**{metric.upper()}**", "", stats.comparison_table(comparisons), ""]
            if metric == "psnr":
                sentences = [verdict_sentence(c) for c in comparisons if c.n_scenes]
        out += ["In words (PSNR): " + " ".join(sentences), ""]
    return "\n".join(out)


def verdict_sentence(c: "stats.Comparison") -> str:
    """One README sentence: a ranking only where the comparison's verdict holds, else "indistinguishable"."""
    d = stats.DIGITS[c.metric]
    gain = f"`{c.selector}` - `{c.baseline}` {c.estimate:+.{d}f} dB, 95% CI [{c.lo:+.{d}f}, {c.hi:+.{d}f}], {c.n_scenes} scenes"
    if c.verdict == stats.INDISTINGUISHABLE:
        return f"`{c.selector}` and `{c.baseline}` are indistinguishable here ({gain})."
    better, worse = (c.selector, c.baseline) if c.lo > 0 else (c.baseline, c.selector)
    kind = "primary" if c.primary else "Holm-adjusted"
    return f"`{better}` beats `{worse}` ({gain}, p = {c.p_adjusted:.3g}, {kind})."


def scenes_table(rows: List[dict]) -> str:
    """Each scene's training and test views and the seeds run (small test sets make PSNR partly a matter of
    which test viewpoints the picks sit near)."""
    lines = ["| scene | training views | test views | seeds |", "|---|---|---|---|"]
    for scene in sorted({r["scene"] for r in rows}):
        group = [r for r in rows if r["scene"] == scene]
        train = max((r.get("num_train_views") or r["num_views_final"] for r in group if r["selector"] == "all"), default=None)
        train = train or max((r.get("num_train_views") or 0 for r in group), default=0) or "?"
        seeds = sorted({r["seed"] for r in group if r["selector"] not in REFERENCES})
        lines.append(f"| {scene} | {train} | {group[0].get('num_test_views', '?')} | {', '.join(map(str, seeds))} |")
    return "\n".join(lines)


def noise_table(rows: List[dict]) -> str:
    """Repeat noise against seed spread: the standard deviation of test PSNR over repeats of one (scene,
    selector, seed), averaged over the seeds that were repeated, beside the one over seeds (repeat 0 of each);
    "" without repeats."""
    repeated: Dict[Tuple[str, str, str], Dict[int, Dict[int, float]]] = {}
    for r in rows:
        key = (r["scene"], r["protocol"], r["selector"])
        repeated.setdefault(key, {}).setdefault(r["seed"], {})[r.get("repeat") or 0] = r["test"]["psnr"]
    keys = [k for k, by_seed in repeated.items() if any(len(v) > 1 for v in by_seed.values())]
    if not keys:
        return ""
    lines = ["| scene | protocol | selector | seeds repeated | runs per repeated seed | repeat SD (dB) | seeds | seed SD (dB) |",
             "|---|---|---|---|---|---|---|---|"]
    for key in sorted(keys):
        by_seed = repeated[key]
        again = {seed: runs for seed, runs in by_seed.items() if len(runs) > 1}
        rep = [_mean_std(list(runs.values()))[1] for runs in again.values()]
        firsts = [runs[0] for runs in by_seed.values() if 0 in runs]
        seed_sd = f"{_mean_std(firsts)[1]:.2f}" if len(firsts) > 1 else "–"
        per_seed = sorted({len(runs) for runs in again.values()})
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {', '.join(map(str, sorted(again)))} | "
                     f"{'/'.join(map(str, per_seed))} | {sum(rep) / len(rep):.2f} | {len(firsts)} | {seed_sd} |")
    return "\n".join(lines) + "\n"


def throughput_table(rows: List[dict]) -> str:
    """Runs per hour per device against how many ran at once, over each busy span of one machine (runs whose
    times overlap, whichever sweep started them: two sweeps sharing a GPU count together); "" without
    timestamps. "At once" is measured from the runs' start and end times, not read from `--runs-per-gpu`."""
    timed = [r for r in rows if _timed(r)]
    if not timed:
        return ""
    spans: List[List[dict]] = []
    end = 0.0  # when the last span's latest run ended
    for r in sorted(timed, key=lambda r: (_machine(r), r["started_at"])):
        if spans and _machine(spans[-1][0]) == _machine(r) and r["started_at"] < end:
            spans[-1].append(r)
        else:
            spans.append([r])
            end = 0.0
        end = max(end, r["started_at"] + r["wall_seconds"])

    def at_once(span: List[dict]) -> int:
        events = sorted([(r["started_at"], 1) for r in span] + [(r["started_at"] + r["wall_seconds"], -1) for r in span])
        running = peak = 0
        for _, change in events:
            running += change
            peak = max(peak, running)
        return peak

    lines = ["| device | runs at once (most) | runs | span (s) | runs per hour | mean wall per run (s) |",
             "|---|---|---|---|---|---|"]
    for span in sorted(spans, key=lambda g: (short_device(g[0]), at_once(g), g[0]["started_at"])):
        length = max(r["started_at"] + r["wall_seconds"] for r in span) - min(r["started_at"] for r in span)
        wall = sum(r["wall_seconds"] for r in span) / len(span)
        lines.append(f"| {short_device(span[0])} | {at_once(span)} | {len(span)} | {length:.0f} | "
                     f"{3600 * len(span) / length:.1f} | {wall:.0f} |")
    return "\n".join(lines) + "\n"


def gain_plot(rows: List[dict], out: Path) -> List[Path]:
    """Per protocol: each selector's paired PSNR gain over random, one dot per (scene, seed), with the mean over
    scenes and its 95% hierarchical-bootstrap interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = comparable(rows)
    paths = []
    for protocol in sorted({r["protocol"] for r in rows}):
        group = [r for r in rows if r["protocol"] == protocol]
        primary, _ = comparison_plan(group, protocol)
        selectors = [a for a, b in primary if b == BASELINE]
        if not selectors:
            continue
        scenes = sorted({r["scene"] for r in group})
        fig, ax = plt.subplots(figsize=(1.6 * len(selectors) + 3, 4))
        for i, sel in enumerate(selectors):
            gains = stats.paired_gains(group, sel, BASELINE, protocol, "psnr")
            for j, scene in enumerate(scenes):
                values = list(gains.get(scene, {}).values())
                xs = [i - 0.25 + 0.5 * (j + 0.5) / len(scenes)] * len(values)
                ax.scatter(xs, values, s=14, color=f"C{j}", label=scene if i == 0 else None, zorder=3)
            if gains:
                est, lo, hi = stats.hierarchical_bootstrap(gains)
                ax.errorbar([i + 0.32], [est], yerr=[[est - lo], [hi - est]], fmt="D", color="k", capsize=4, zorder=4)
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_xticks(range(len(selectors)), selectors)
        ax.set(ylabel="test PSNR gain over random (dB)",
               title=f"{protocol}: paired gain over random (dots: scene x seed; diamond: mean over scenes, 95% CI)")
        ax.title.set_fontsize(9)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)  # outside: no dot hidden
        fig.tight_layout()
        path = save_figure(fig, out / f"{protocol}-paired-gains.png")
        paths.append(path)
    return paths


def write_report(out: Path, readme: Optional[Path] = None) -> List[Path]:
    """Every table and plot of a results folder; with `readme`, its results section too (between
    `<!-- bench:OUT:begin -->` and `<!-- bench:OUT:end -->`). Returns the files written."""
    rows = load_results(out)
    written = []
    sections = {"table.md": markdown_table(rows), "paired.md": paired_report(rows), "work.md": work_table(rows),
                "noise.md": noise_table(rows), "throughput.md": throughput_table(rows), "stress.md": stress_table(rows)}
    for name, text in sections.items():
        if text:
            written.append(write_text_atomic(out / name, text))
    written += stress_plot(rows, out) + make_plots(rows, out) + gain_plot(rows, out)
    if readme is not None:
        written.append(replace_section(readme, f"bench:{out.as_posix()}", results_section(out, sections)))
    return written


def results_section(out: Path, sections: Dict[str, str]) -> str:
    parts = [f"Built by `hpgs bench --out {out.as_posix()} --report-only`; every comparison pairs runs by scene and seed.", ""]
    if sections["paired.md"]:
        parts += [sections["paired.md"]]
    for name, title in (("noise.md", "Repeat noise against seed spread"), ("throughput.md", "Throughput")):
        if sections[name]:
            parts += [f"**{title}**", "", sections[name]]
    return "\n".join(parts)


def replace_section(path: Path, marker: str, text: str) -> Path:
    """Replace what lies between `<!-- MARKER:begin -->` and `<!-- MARKER:end -->` in `path` (one-line error when
    the markers are missing)."""
    begin, end = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    doc = Path(path).read_text()
    if begin not in doc or end not in doc:
        raise SystemExit(f"hpgs bench: {path} has no {begin} ... {end} markers; add them where the results go")
    head, rest = doc.split(begin, 1)
    _, tail = rest.split(end, 1)
    return write_text_atomic(path, f"{head}{begin}\n{text.strip()}\n{end}{tail}")
