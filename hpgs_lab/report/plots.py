"""The report's figures: PSNR against run time and against the step of each round, camera maps, stress bars and
paired gains. matplotlib is imported inside each function (Agg backend): the tables need none of it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from hpgs_lab import stats
from hpgs_lab.report.paired import BASELINE, comparable, comparison_plan
from hpgs_lab.report.tables import paired_change, psnr_by_seed, short_device, stress_groups
from hpgs_lab.results import RunResult
from hpgs_ns.atomic_write import atomic_path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, rect=(0, 0, 1, 1)) -> Path:
    """Lay out, write (temp file, then rename) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout(rect=rect)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return Path(path)


def make_plots(rows: Sequence[RunResult], out: Path) -> List[Path]:
    """PSNR vs wall time per selector, and PSNR at each selection round's step, per (scene, protocol)."""
    plt = _pyplot()
    paths = []
    keys = sorted({(r.scene, r.protocol) for r in rows})
    for scene, protocol in keys:
        group = [r for r in rows if r.scene == scene and r.protocol == protocol]
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
        # One marker per device: run times are only comparable on one device.
        markers = dict(zip(sorted({short_device(r) for r in group}), "o^sDvP"))
        for i, sel in enumerate(sorted({r.selector for r in group})):
            rs = [r for r in group if r.selector == sel]
            for n, r in enumerate(rs):
                ax1.scatter(r.timing.wall_seconds, r.test.psnr, s=30, color=f"C{i}",
                            marker=markers[short_device(r)], label=sel if n == 0 else None)
            if rs[0].is_reference:
                continue
            for k, r in enumerate(rs):
                # Against the step, not the view count: early rounds' PSNR is mostly training progress, and a
                # views axis read it as the views' doing.
                pts = [(p.step, p.test_psnr) for p in r.psnr_per_round if p.test_psnr is not None]
                if r.steps is not None:
                    pts.append((r.steps, r.test.psnr))
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


def camera_map(group: Sequence[RunResult], path: Path) -> Optional[Path]:
    """One panel per selector (first seed): all cameras, the initial views, and the chosen ones numbered."""
    import matplotlib.pyplot as plt

    runs = [r for r in sorted(group, key=lambda r: r.seed) if not r.is_reference and r.chosen_views]
    if not runs:
        return None
    scene = Path(runs[0].data) if runs[0].data else None
    pos = camera_centres(scene) if scene is not None and scene.is_dir() else None
    if not pos:
        return None
    first: Dict[str, RunResult] = {}
    for r in runs:
        first.setdefault(r.selector, r)

    def at(name: str) -> Optional[Tuple[float, float]]:
        # a view name, a COLMAP image name (the view name without its image folder), or a 0.1 bare file name
        return pos.get(name) or pos.get(Path(*Path(name).parts[1:]).as_posix() if len(Path(name).parts) > 1 else name)

    fig, axes = plt.subplots(1, len(first), figsize=(3.6 * len(first), 3.6), squeeze=False)
    all_xy = list(pos.values())
    for ax, (sel, r) in zip(axes[0], sorted(first.items())):
        ax.scatter(*zip(*all_xy), s=6, c="lightgrey", label="withheld / test")
        initial = [xy for xy in map(at, r.initial_views) if xy is not None]
        if initial:
            ax.scatter(*zip(*initial), s=12, c="C0", label="initial")
        chosen = [(k, at(name)) for k, name in enumerate(r.chosen_views, 1) if at(name) is not None]
        if chosen:
            ax.scatter(*zip(*[xy for _, xy in chosen]), s=30, c="C3", label="added (in order)")
        for k, xy in chosen:
            ax.annotate(str(k), xy, fontsize=8, xytext=(3, 3), textcoords="offset points")
        ax.set(title=f"{sel} (seed {r.seed})", xticks=[], yticks=[], aspect="equal")
    # Below the panels: inside one it would hide cameras.
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="lower center", ncol=3, fontsize=8, frameon=False)
    save_figure(fig, path, rect=(0, 0.07, 1, 1))
    return path


def stress_plot(rows: Sequence[RunResult], out: Path) -> List[Path]:
    """Per (scene, protocol): bars of the PSNR change from clean (paired by seed), one group per selector, one bar
    per perturbation."""
    plt = _pyplot()
    psnr = psnr_by_seed(rows)
    paths = []
    for base, protocol, perturbations, selectors in stress_groups(psnr):
        selectors = [s for s in selectors if any(paired_change(psnr, (base, protocol, s, p)) is not None for p in perturbations)]
        if not selectors:
            continue
        fig, ax = plt.subplots(figsize=(1.4 * len(selectors) + 2, 3.6))
        width = 0.8 / len(perturbations)
        for j, p in enumerate(perturbations):
            xs = [i + (j - (len(perturbations) - 1) / 2) * width for i in range(len(selectors))]
            drops = [paired_change(psnr, (base, protocol, s, p)) for s in selectors]
            ax.bar(xs, [float("nan") if d is None else d for d in drops], width, label=p)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xticks(range(len(selectors)), selectors)
        ax.set(ylabel="test PSNR change from clean (dB)", title=f"{base} / {protocol}: stress (same seeds)")
        ax.legend(fontsize=8)
        path = save_figure(fig, out / f"{base}-{protocol}-stress.png")
        paths.append(path)
    return paths


def scene_style(index: int) -> dict:
    """Colour and marker of the index-th scene: matplotlib's cycle has ten colours, so every ten scenes the marker
    changes (twelve scenes in colours alone showed two pairs alike)."""
    return {"color": f"C{index % 10}", "marker": "o^sDv"[index // 10 % 5]}


def gain_plot(rows: Sequence[RunResult], out: Path) -> List[Path]:
    """Per protocol: each selector's paired PSNR gain over random, one dot per (scene, seed), with the mean over
    scenes and its 95% hierarchical-bootstrap interval."""
    plt = _pyplot()
    rows = comparable(rows)
    paths = []
    for protocol in sorted({r.protocol for r in rows}):
        group = [r for r in rows if r.protocol == protocol]
        primary, _ = comparison_plan(group, protocol)
        selectors = [a for a, b in primary if b == BASELINE]
        if not selectors:
            continue
        scenes = sorted({r.scene for r in group})
        fig, ax = plt.subplots(figsize=(1.6 * len(selectors) + 3, 4))
        for i, sel in enumerate(selectors):
            gains = stats.paired_gains(group, sel, BASELINE, protocol, "psnr")
            for j, scene in enumerate(scenes):
                values = list(gains.get(scene, {}).values())
                xs = [i - 0.25 + 0.5 * (j + 0.5) / len(scenes)] * len(values)
                ax.scatter(xs, values, s=14, **scene_style(j), label=scene if i == 0 else None, zorder=3)
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
