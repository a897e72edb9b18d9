"""`hpgs bench`'s report: the results table, what selection computed, plots, and stress mode's tables.

Everything here reads the per-run JSON (`load_results`) and writes nothing but tables and figures, so
`hpgs bench --report-only` can rebuild it from any results folder.
"""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from hpgs_ns.bench.protocols import REFERENCES, row_order


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


def markdown_table(rows: List[dict]) -> str:
    """Mean +- std over seeds per (scene, protocol, selector)."""
    groups: Dict[Tuple[str, str, str], List[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["protocol"], r["selector"]), []).append(r)
    lines = [
        "| scene | protocol | selector | seeds | views | PSNR | SSIM | LPIPS | devices | wall (s) | selection (s) |",
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
        wall, _ = _mean_std([g["wall_seconds"] for g in group])
        selt, _ = _mean_std([g["selection_seconds"] for g in group])
        views = group[0]["num_views_final"]
        devices = device_counts(group)
        lines.append(
            f"| {scene} | {protocol} | {sel} | {len(group)} | {views} | {' | '.join(cells)} | {devices} | {wall:.0f} | {selt:.1f} |"
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
    """PSNR vs wall time per selector, PSNR vs number of views, per (scene, protocol)."""
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
                pts = [(p["num_views_before"], p["test_psnr"]) for p in r["psnr_per_round"] if p["test_psnr"] is not None]
                pts.append((r["num_views_final"], r["test"]["psnr"]))
                ax2.plot(*zip(*pts), marker="o", ms=3, color=f"C{i}",
                         label=sel if k == 0 else None, alpha=0.8)
        ax1.set(xlabel="wall time (s)", ylabel="test PSNR (dB)", title=f"{scene} / {protocol}: PSNR vs run time")
        ax2.set(xlabel="training views", ylabel="test PSNR (dB)", title="PSNR as views are added")
        handles, labels = ax1.get_legend_handles_labels()
        if len(markers) > 1:
            for device, marker in markers.items():
                handles.append(ax1.scatter([], [], marker=marker, color="grey", s=30))
                labels.append(device)
        ax1.legend(handles, labels, fontsize=8)
        ax2.legend(fontsize=8)
        fig.tight_layout()
        path = out / f"{scene}-{protocol}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
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
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
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
        fig.tight_layout()
        path = out / f"{base}-{protocol}-stress.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
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
