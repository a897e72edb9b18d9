"""The report's markdown tables: results per row, selection work, repeat noise, throughput, stress, scenes.

Means and spreads here are for reading; which selector beats which is decided in `paired` only.
"""

from __future__ import annotations

import math
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

from hpgs_lab.names import ALL
from hpgs_lab.protocols import row_order
from hpgs_lab.results import RunResult

METRICS = ("psnr", "ssim", "lpips")


def mean_std(values: Sequence[float]) -> Tuple[float, float]:
    """Mean and sample standard deviation (0 for one value)."""
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else 0.0
    return mean, std


def _mean(values) -> float:
    values = list(values)
    return sum(values) / len(values)


def bench_order() -> Dict[str, int]:
    """Selector or reference name -> its place in tables (registry order, then the reference rows)."""
    return {name: i for i, name in enumerate(row_order())}


def short_device(row: RunResult) -> str:
    """`NVIDIA H100 80GB HBM3` -> `H100`, `cpu x2` -> `cpu`."""
    return str(row.device).replace("NVIDIA ", "").split()[0]


def device_counts(group: Sequence[RunResult]) -> str:
    """`H100 x2, H200`: wall times are only comparable on one device, and sweeps span sessions and machines."""
    counts: Dict[str, int] = {}
    for g in group:
        counts[short_device(g)] = counts.get(short_device(g), 0) + 1
    return ", ".join(name if n == 1 else f"{name} x{n}" for name, n in sorted(counts.items()))


def timed(row: RunResult) -> bool:
    """Whether a run recorded when it ran, and on which machine (its sweep id)."""
    t = row.timing
    return bool(t.sweep_id and t.started_at is not None and t.wall_seconds)


def machine(row: RunResult) -> Tuple[str, str, str]:
    """(device, host of the sweep, GPU): runs of two sweeps on one GPU of a machine share it (runs that did not
    record their GPU count as sharing every GPU of their host)."""
    return short_device(row), str(row.timing.sweep_id).rsplit("-", 1)[0], str(row.timing.gpu or "")


def _end(row: RunResult) -> float:
    return row.timing.started_at + row.timing.wall_seconds  # type: ignore[operator]


def solo(row: RunResult, rows: Sequence[RunResult] = ()) -> bool:
    """Whether a run had its GPU to itself (its wall and per-step times then mean what they say): one run per GPU,
    and no run among `rows` on the same machine overlapping it in time (two sweeps can share one GPU)."""
    if int(row.timing.runs_per_gpu) != 1:
        return False
    if not timed(row):
        return True
    start, end = row.timing.started_at, _end(row)
    return not any(r is not row and timed(r) and machine(r) == machine(row)
                   and r.timing.started_at < end and start < _end(r) for r in rows)


def markdown_table(rows: Sequence[RunResult]) -> str:
    """Mean +- std over seeds per (scene, protocol, selector); times from solo runs only (one run per GPU and no
    other sweep's run beside it; "–" when every run of the row shared its GPU). Repeats (`--repeats`) are left out."""
    groups: Dict[Tuple[str, str, str], List[RunResult]] = {}
    for r in rows:
        if not r.repeat:
            groups.setdefault((r.scene, r.protocol, r.selector), []).append(r)
    lines = [
        "| scene | protocol | selector | seeds | views | PSNR | SSIM | LPIPS | devices | wall (s, solo) | selection (s, solo) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    order = bench_order()
    for (scene, protocol, sel), group in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], order.get(kv[0][2], 99))):
        cells = []
        for key in METRICS:
            m, s = mean_std([g.test.value(key) for g in group])
            digits = 2 if key == "psnr" else 3
            # One seed has no spread to show (a "± 0.00" would read as a measured one).
            cells.append(f"{m:.{digits}f} ± {s:.{digits}f}" if len(group) > 1 else f"{m:.{digits}f}")
        alone = [g for g in group if solo(g, rows)]
        wall = f"{mean_std([g.timing.wall_seconds for g in alone])[0]:.0f}" if alone else "–"
        selt = f"{mean_std([g.timing.selection_seconds for g in alone])[0]:.1f}" if alone else "–"
        views = group[0].num_views_final
        devices = device_counts(group)
        lines.append(
            f"| {scene} | {protocol} | {sel} | {len(group)} | {views} | {' | '.join(cells)} | {devices} | {wall} | {selt} |"
        )
    return "\n".join(lines) + "\n"


def work_table(rows: Sequence[RunResult]) -> str:
    """What selection computed and what it skipped, per selector (mean over runs): renders at the size the
    selector needs vs the dataset's, Fisher's frustum-culled (view, Gaussian) pairs vs all of them."""
    groups: Dict[Tuple[str, str, str], List[RunResult]] = {}
    for r in rows:
        if r.selection_work:
            groups.setdefault((r.scene, r.protocol, r.selector), []).append(r)
    if not groups:
        return ""
    lines = [
        "| scene | protocol | selector | views rendered | pixels vs full size | pairs vs unculled | backward passes "
        "| forwards | selection (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def mean(group: List[RunResult], key: str) -> float:
        return sum(g.selection_work.get(key, 0.0) for g in group) / len(group)

    for (scene, protocol, sel), group in sorted(groups.items()):
        full, pairs_all = mean(group, "pixels_full_resolution"), mean(group, "pairs_unculled")
        pixels = f"{100 * mean(group, 'pixels_rendered') / full:.0f}%" if full else "-"
        pairs = f"{100 * mean(group, 'pairs_differentiated') / pairs_all:.0f}%" if pairs_all else "-"
        seconds = sum(g.timing.selection_seconds for g in group) / len(group)
        lines.append(
            f"| {scene} | {protocol} | {sel} | {mean(group, 'views_rendered'):.0f} | {pixels} | {pairs} | "
            f"{mean(group, 'backward_passes'):.0f} | {mean(group, 'model_forwards'):.0f} | {seconds:.1f} |"
        )
    return "\n".join(lines) + "\n"


def scenes_table(rows: Sequence[RunResult]) -> str:
    """Each scene's training and test views and the seeds run (small test sets make PSNR partly a matter of
    which test viewpoints the picks sit near)."""
    lines = ["| scene | training views | test views | seeds | seed points |", "|---|---|---|---|---|"]
    for scene in sorted({r.scene for r in rows}):
        group = [r for r in rows if r.scene == scene]
        train = max((r.num_train_views or r.num_views_final for r in group if r.selector == ALL), default=None)
        train = train or max((r.num_train_views or 0 for r in group), default=0) or "?"
        seeds = sorted({r.seed for r in group if not r.is_reference})
        tests = group[0].num_test_views
        starts = ", ".join(sorted({r.start or "not recorded" for r in group}))  # which start each number used
        lines.append(f"| {scene} | {train} | {'?' if tests is None else tests} | {', '.join(map(str, seeds))} | {starts} |")
    return "\n".join(lines)


def noise_table(rows: Sequence[RunResult]) -> str:
    """Repeat noise against seed spread: the standard deviation of test PSNR over repeats of one (scene,
    selector, seed), averaged over the seeds that were repeated, beside the one over seeds (repeat 0 of each);
    "" without repeats."""
    repeated: Dict[Tuple[str, str, str], Dict[int, Dict[int, float]]] = {}
    for r in rows:
        key = (r.scene, r.protocol, r.selector)
        repeated.setdefault(key, {}).setdefault(r.seed, {})[r.repeat] = r.test.psnr
    keys = [k for k, by_seed in repeated.items() if any(len(v) > 1 for v in by_seed.values())]
    if not keys:
        return ""
    lines = ["| scene | protocol | selector | seeds repeated | runs per repeated seed | repeat SD (dB) | seeds | seed SD (dB) |",
             "|---|---|---|---|---|---|---|---|"]
    for key in sorted(keys):
        by_seed = repeated[key]
        again = {seed: runs for seed, runs in by_seed.items() if len(runs) > 1}
        rep = [mean_std(list(runs.values()))[1] for runs in again.values()]
        firsts = [runs[0] for runs in by_seed.values() if 0 in runs]
        seed_sd = f"{mean_std(firsts)[1]:.2f}" if len(firsts) > 1 else "–"
        per_seed = sorted({len(runs) for runs in again.values()})
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {', '.join(map(str, sorted(again)))} | "
                     f"{'/'.join(map(str, per_seed))} | {sum(rep) / len(rep):.2f} | {len(firsts)} | {seed_sd} |")
    return "\n".join(lines) + "\n"


def mps_seen(span: Sequence[RunResult]) -> str:
    """`yes` when every run of a span was seen as an MPS client, `no` when none was, `some`, or `–` (not recorded)."""
    seen = {r.timing.mps for r in span}
    if seen == {None}:
        return "–"
    return "yes" if seen == {True} else "no" if seen <= {False, None} else "some"


def throughput_table(rows: Sequence[RunResult]) -> str:
    """Runs per hour per device against how many ran at once, over each busy span of one machine (runs whose
    times overlap, whichever sweep started them: two sweeps sharing a GPU count together); "" without
    timestamps. "At once" is measured from the runs' start and end times, not read from `--runs-per-gpu`."""
    timed_rows = [r for r in rows if timed(r)]
    if not timed_rows:
        return ""
    spans: List[List[RunResult]] = []
    end = 0.0  # when the last span's latest run ended
    key = lambda r: (machine(r), str(r.timing.mps))  # noqa: E731  (runs with and without MPS are apart)
    for r in sorted(timed_rows, key=lambda r: (key(r), r.timing.started_at)):
        if spans and key(spans[-1][0]) == key(r) and r.timing.started_at < end:
            spans[-1].append(r)
        else:
            spans.append([r])
            end = 0.0
        end = max(end, _end(r))

    def at_once(span: List[RunResult]) -> int:
        events = sorted([(r.timing.started_at, 1) for r in span] + [(_end(r), -1) for r in span])
        running = peak = 0
        for _, change in events:
            running += change
            peak = max(peak, running)
        return peak

    lines = ["| device | MPS | runs at once (most) | runs | span (s) | runs per hour | mean wall per run (s) |",
             "|---|---|---|---|---|---|---|"]
    for span in sorted(spans, key=lambda g: (short_device(g[0]), mps_seen(g), at_once(g), g[0].timing.started_at)):
        length = max(_end(r) for r in span) - min(r.timing.started_at for r in span)
        wall = sum(r.timing.wall_seconds for r in span) / len(span)
        lines.append(f"| {short_device(span[0])} | {mps_seen(span)} | {at_once(span)} | {len(span)} | {length:.0f} | "
                     f"{3600 * len(span) / length:.1f} | {wall:.0f} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------------------
# Stress mode: how much each selector loses on perturbed copies (`hpgs bench --stress`)


def split_scene_name(scene: str) -> Tuple[str, str]:
    """`"ring+exposure"` -> `("ring", "exposure")`; a clean scene's perturbation is `"clean"`."""
    base, _, perturbation = scene.partition("+")
    return base, perturbation or "clean"


Key = Tuple[str, str, str, str]  # (base scene, protocol, selector, perturbation)


def psnr_by_seed(rows: Sequence[RunResult]) -> Dict[Key, Dict[int, float]]:
    """(base scene, protocol, selector, perturbation) -> {seed: test PSNR}."""
    values: Dict[Key, Dict[int, float]] = {}
    for r in rows:
        base, perturbation = split_scene_name(r.scene)
        values.setdefault((base, r.protocol, r.selector, perturbation), {})[r.seed] = r.test.psnr
    return values


def paired_change(psnr: Dict[Key, Dict[int, float]], key: Key) -> Optional[float]:
    """Mean over seeds of (perturbed - clean), on the seeds run both ways: seeds differ in their initial views,
    so a perturbed seed is only compared with the same seed's clean run. None without a common seed."""
    clean = psnr.get(key[:3] + ("clean",), {})
    seeds = sorted(set(psnr.get(key, {})) & set(clean))
    return _mean(psnr[key][s] - clean[s] for s in seeds) if seeds else None


def stress_groups(psnr: Dict[Key, Dict[int, float]]) -> Iterator[Tuple[str, str, List[str], List[str]]]:
    """(base, protocol, perturbations, selectors in bench order) for every group with a perturbed run."""
    order = bench_order()
    for base, protocol in sorted({k[:2] for k in psnr if k[3] != "clean"}):
        keys = [k for k in psnr if k[:2] == (base, protocol)]
        perturbations = sorted({k[3] for k in keys if k[3] != "clean"})
        selectors = sorted({k[2] for k in keys}, key=lambda s: (order.get(s, 99), s))
        yield base, protocol, perturbations, selectors


def stress_table(rows: Sequence[RunResult]) -> str:
    """Per scene and protocol with perturbed runs: test PSNR per selector, clean and under each perturbation, with
    the change from clean in dB paired by seed; "" when no row is from a perturbed scene."""
    psnr = psnr_by_seed(rows)
    lines = []
    for base, protocol, perturbations, selectors in stress_groups(psnr):
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
                change = paired_change(psnr, (base, protocol, sel, p))
                drops.append(change)
                mean = _mean(runs.values())
                cells.append(f"{mean:.2f}" if change is None else f"{mean:.2f} ({change:+.2f})")
            # Averaged only over a full row: a mean of some perturbations is not comparable with one of all.
            full = len(drops) == len(perturbations) and None not in drops
            avg = f"{_mean(drops):+.2f}" if full else "–"
            lines.append(f"| {sel} | {clean_cell} | {' | '.join(cells)} | {avg} |")
        lines.append("")
    return "\n".join(lines)
