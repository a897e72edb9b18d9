"""`fisher`'s criteria (`trace`, POp-GS's `dopt` and `dopt-block`) against brute-force Hessians, and their greedy joint
choice of several views against brute force and the exhaustive best.

The brute force takes the full Jacobian of a plain render (the model's own rasterization call) of a 30-Gaussian
splat at 8x6 pixels with torch.autograd, per view, and builds every criterion from it with slogdet."""

from __future__ import annotations

import functools
import itertools
import math
from contextlib import contextmanager
from typing import Dict, List

import pytest
import torch
import tyro
from nerfstudio.cameras.cameras import Cameras

from hpgs_ns.cpu_raster import rasterization
from hpgs_ns.errors import OptionError
from hpgs_ns.render.pair_render import Splat, render_pairs
from hpgs_ns.render.rasterize import rasterize_splat
from hpgs_ns.render.viewmats import world_to_camera
from hpgs_ns.selectors.base import SelectionContext
from hpgs_ns.selectors.fisher import FisherSelectorConfig, block_logdet_gain, dopt_gain, greedy_joint, trace_gain

torch.set_num_threads(1)
W, H = 8, 6
ORDER = ("means", "features_dc", "features_rest", "scales", "opacities", "quats")  # the brute force's column order
BLOCK = ("means", "features_dc", "scales", "opacities")  # dopt-block's block rows, in order (+ quats)


def random_splat(n: int = 30, sh_degree: int = 1, seed: int = 0) -> Splat:
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    params = {
        "means": torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5,
        "scales": torch.log(torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.25 + 0.15),
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "opacities": torch.randn(n, 1, generator=g, dtype=torch.float64),
        "features_dc": torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5,
        "features_rest": torch.randn(n, k - 1, 3, generator=g, dtype=torch.float64) * 0.2,
    }
    return Splat(params=params, sh_degree=sh_degree, background=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))


def ring_cameras(n: int = 5, radius: float = 3.0) -> Cameras:
    """n nerfstudio cameras (OpenGL, camera-to-world) around the origin at varying heights, looking at it."""
    c2w = []
    for k in range(n):
        a = 2 * math.pi * k / n
        centre = torch.tensor([radius * math.cos(a), radius * math.sin(a), 0.5 * math.sin(3 * a)], dtype=torch.float64)
        back = centre / centre.norm()
        right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), back)
        right = right / right.norm()
        c2w.append(torch.stack([right, torch.linalg.cross(back, right), back, centre], dim=1))
    return Cameras(camera_to_worlds=torch.stack(c2w), fx=5.0, fy=5.0, cx=W / 2, cy=H / 2, width=W, height=H)


class StandIn:
    """What `fisher` reads of the model: `splat()` and `eval_mode()`."""

    def __init__(self, splat: Splat) -> None:
        self._splat = splat

    def splat(self) -> Splat:
        return self._splat

    @contextmanager
    def eval_mode(self):
        yield self


def context(splat: Splat, cams: Cameras, active, candidates, k: int = 1, seed: int = 0) -> SelectionContext:
    return SelectionContext(
        step=100, round_index=0, active=list(active), candidates=list(candidates), num_to_pick=k, cameras=cams,
        image_names=[f"{i:03d}.png" for i in range(len(cams))], model=StandIn(splat), render=None,  # type: ignore[arg-type]
        generator=torch.Generator().manual_seed(seed),
    )


def brute_force_blocks(splat: Splat, cams: Cameras, view: int) -> torch.Tensor:
    """[N, P, P] each Gaussian's full J^T J for `view`, columns in ORDER (every parameter, quats included), from
    torch.autograd.functional.jacobian of a plain render."""
    viewmat = world_to_camera(cams.camera_to_worlds[view : view + 1])
    K = cams.get_intrinsics_matrices()[view : view + 1].to(torch.float64)

    def image(*tensors):
        params = dict(zip(ORDER, tensors, strict=True))
        img, alpha, _ = rasterize_splat(rasterization, params, splat.sh_degree, viewmat, K, W, H)
        return (img + (1 - alpha) * splat.background).reshape(-1)

    jac = torch.autograd.functional.jacobian(image, tuple(splat.params[n] for n in ORDER))
    n = splat.num_points
    per_gauss = torch.cat([j.reshape(j.shape[0], n, -1) for j in jac], 2)  # [pixels * 3, N, P]
    return torch.einsum("rgi,rgj->gij", per_gauss, per_gauss)


def columns(splat: Splat) -> Dict[str, slice]:
    out, start = {}, 0
    for name in ORDER:
        width = splat.params[name][0].numel()
        out[name] = slice(start, start + width)
        start += width
    return out


def brute_force_scores(splat: Splat, blocks: Dict[int, torch.Tensor], active, candidates, criterion: str,
                       rotations: bool, reg: float = 1e-6, rel: float = 1e-2) -> Dict[int, float]:
    """Every criterion written out from the full blocks: lambda per parameter tensor from H_train's diagonal,
    trace/dopt over diagonals, dopt-block by slogdet over each Gaussian's block rows plus dopt over the SH rest."""
    cols = columns(splat)
    names = [n for n in ORDER if rotations or n != "quats"]
    train = sum(blocks[v] for v in active)
    diag_train = train.diagonal(dim1=-2, dim2=-1)
    lam = {n: reg + rel * float(diag_train[:, cols[n]].mean()) for n in names}
    scores = {}
    for c in candidates:
        diag_c = blocks[c].diagonal(dim1=-2, dim2=-1)
        if criterion in ("trace", "dopt"):
            total = 0.0
            for n in names:
                ratio = diag_c[:, cols[n]] / (diag_train[:, cols[n]] + lam[n])
                total += float(ratio.sum() if criterion == "trace" else torch.log(1 + ratio).sum())
            scores[c] = total
            continue
        rows = torch.cat([torch.arange(cols[n].start, cols[n].stop) for n in BLOCK + (("quats",) if rotations else ())])
        lam_rows = torch.cat([torch.full((cols[n].stop - cols[n].start,), lam[n], dtype=torch.float64)
                              for n in BLOCK + (("quats",) if rotations else ())])
        a = train[:, rows][:, :, rows] + torch.diag(lam_rows)
        b = blocks[c][:, rows][:, :, rows]
        total = float((torch.linalg.slogdet(a + b)[1] - torch.linalg.slogdet(a)[1]).sum())
        rest = cols["features_rest"]
        total += float(torch.log(1 + diag_c[:, rest] / (diag_train[:, rest] + lam["features_rest"])).sum())
        scores[c] = total
    return scores


@pytest.fixture(scope="module")
def scene():
    splat, cams = random_splat(), ring_cameras()
    return splat, cams, {v: brute_force_blocks(splat, cams, v) for v in range(len(cams))}


ACTIVE, CANDIDATES = [0, 2], [1, 3, 4]
FAST = {}  # the defaults: linearize (SH through the colour gradient)
DIRECT = {"include_rotations": True, "linearize": False, "sh_via_color": False}  # every gradient back-propagated
VIA_COLOUR = {"linearize": False}  # the SH through the colour gradient, without linearizing


# ---- 1. each criterion against brute-force Hessians -------------------------------------------------------------


@pytest.mark.parametrize("criterion, options", [("trace", FAST), ("dopt", FAST), ("dopt-block", FAST),
                                                ("dopt-block", DIRECT), ("dopt-block", VIA_COLOUR)],
                         ids=["trace", "dopt", "dopt-block", "dopt-block-direct", "dopt-block-via-colour"])
def test_criteria_equal_their_formulas_on_brute_force_hessians(scene, criterion, options):
    splat, cams, blocks = scene
    config = FisherSelectorConfig(criterion=criterion, mode="exact", resolution_scale=1.0, **options)
    scores = config.setup().select(context(splat, cams, ACTIVE, CANDIDATES)).scores
    expected = brute_force_scores(splat, blocks, ACTIVE, CANDIDATES, criterion, options.get("include_rotations", False))
    assert [scores[c] for c in CANDIDATES] == pytest.approx([expected[c] for c in CANDIDATES], rel=1e-9)
    assert min(expected.values()) > 1.0 and len({round(s, 3) for s in expected.values()}) == len(CANDIDATES)


def test_the_criteria_rank_differently_on_the_same_hessians(scene):
    """The three criteria are different numbers of the same Hessians (so the test above tells them apart)."""
    splat, cams, blocks = scene
    trace, dopt, block = (brute_force_scores(splat, blocks, ACTIVE, CANDIDATES, c, False)
                          for c in ("trace", "dopt", "dopt-block"))
    assert all(block[c] != pytest.approx(dopt[c], rel=1e-3) for c in CANDIDATES)
    assert sorted(CANDIDATES, key=trace.get) != sorted(CANDIDATES, key=dopt.get)


def test_dopt_block_probe_blocks_converge_to_the_exact_blocks(scene):
    """E[g g^T] = J^T J for g = J^T eps: the probe mean of each pair's gradient outer product tends to the exact block
    (Frobenius error over all pairs ~ 1/sqrt(probes)), and the SH rest's diagonal to its exact one."""
    splat, cams, _ = scene
    viewmats, Ks = world_to_camera(cams.camera_to_worlds[:2]), cams.get_intrinsics_matrices()[:2]
    exact_sel = FisherSelectorConfig(criterion="dopt-block", mode="exact").setup()
    probe_sel = FisherSelectorConfig(criterion="dopt-block").setup()

    def blocks(selector, probes):
        pr = render_pairs(splat, viewmats, Ks, W, H, selector.param_names(), sh_via_color=True, drop_hidden=True,
                          linearize=True)
        return selector.pair_blocks(pr, probes, torch.Generator().manual_seed(11))

    exact = blocks(exact_sel, 1)
    assert exact["block"].shape[1:] == (10, 10) and exact["features_rest"].shape[1:] == (3, 3)
    off_diagonal = exact["block"] - torch.diag_embed(exact["block"].diagonal(dim1=-2, dim2=-1))
    assert off_diagonal.norm() > 0.3 * exact["block"].norm()  # the block is far from its diagonal
    errors = {}
    for probes in (16, 256):
        estimate = blocks(probe_sel, probes)
        errors[probes] = [float((estimate[k] - exact[k]).norm() / exact[k].norm()) for k in ("block", "features_rest")]
    assert all(e < 0.15 for e in errors[256]), errors
    assert all(many < 0.5 * few for many, few in zip(errors[256], errors[16], strict=True)), errors  # 1/4 expected


# ---- 2. the greedy joint choice ------------------------------------------------------------------------------------


def logdet_objective(per_view: torch.Tensor, h_train: torch.Tensor, lam: torch.Tensor, chosen) -> float:
    """f(S) = logdet(A + sum_S H_v) - logdet(A), A = h_train + lam, summed over blocks (slogdet; diagonals as
    diagonal matrices)."""
    if per_view.dim() == 2:  # diagonals [V, P]
        per_view, h_train, lam = torch.diag_embed(per_view)[:, None], torch.diag(h_train)[None], lam
    a = h_train + torch.diag(lam)
    total = a + sum((per_view[v] for v in chosen), torch.zeros_like(a))
    return float((torch.linalg.slogdet(total)[1] - torch.linalg.slogdet(a)[1]).sum())


def brute_force_greedy(objective, views: List[int], k: int) -> List[int]:
    picked: List[int] = []
    for _ in range(k):
        gains = {v: objective(picked + [v]) - objective(picked) for v in views if v not in picked}
        picked.append(max(gains, key=gains.get))
    return picked


def random_blocks(views: int = 8, gaussians: int = 4, p: int = 3, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(views, gaussians, p, 2, generator=g, dtype=torch.float64)
    y = torch.randn(gaussians, p, 1, generator=g, dtype=torch.float64)
    return x @ x.transpose(-1, -2), y @ y.transpose(-1, -2), torch.tensor([0.1, 0.2, 0.05], dtype=torch.float64)


def random_diagonals(seed: int = 0):
    """Views 0 and 1 carry the same strong information: the greedy joint choice takes only one of them."""
    g = torch.Generator().manual_seed(seed)
    per_view = torch.zeros(8, 20, dtype=torch.float64)
    per_view[:2, :5] = 10.0
    per_view[2:, 5:] = torch.rand(6, 15, generator=g, dtype=torch.float64) * 0.5
    h_train = torch.rand(20, generator=g, dtype=torch.float64)
    return per_view, h_train, torch.full((20,), 0.05, dtype=torch.float64)


@pytest.mark.parametrize("kind", ["diagonal", "block"])
def test_greedy_joint_is_the_brute_force_greedy_within_1_minus_1_over_e_of_the_best_set(kind):
    per_view, h_train, lam = random_diagonals() if kind == "diagonal" else random_blocks()
    gain = functools.partial(dopt_gain if kind == "diagonal" else block_logdet_gain, lam=lam)
    picked, first = greedy_joint(gain, per_view, h_train, 3)
    objective = functools.partial(logdet_objective, per_view, h_train, lam)
    assert picked == brute_force_greedy(objective, list(range(8)), 3)
    assert first.tolist() == pytest.approx([objective([v]) for v in range(8)], rel=1e-10)
    best = max(objective(list(s)) for s in itertools.combinations(range(8), 3))
    assert best >= objective(picked) >= (1 - 1 / math.e) * best
    if kind == "diagonal":
        assert picked[0] in (0, 1) and len({0, 1} & set(picked)) == 1  # the duplicate's marginal gain collapsed
        assert sorted(range(8), key=lambda v: -float(first[v]))[:2] == [0, 1]  # though the single gains rank it 2nd


def test_greedy_joint_under_trace_adds_each_pick_to_h_train():
    per_view, h_train, lam = random_diagonals(1)

    def trace_objective_gain(chosen, v):
        return float((per_view[v] / (h_train + per_view[chosen].sum(0) + lam)).sum())

    picked, _ = greedy_joint(functools.partial(trace_gain, lam=lam), per_view, h_train, 3)
    expected: List[int] = []
    for _ in range(3):
        gains = {v: trace_objective_gain(expected, v) for v in range(8) if v not in expected}
        expected.append(max(gains, key=gains.get))
    assert picked == expected


@pytest.mark.parametrize("kind", ["diagonal", "block"])
def test_greedy_joint_of_one_view_is_the_argmax_of_the_single_view_gains(kind):
    per_view, h_train, lam = random_diagonals(2) if kind == "diagonal" else random_blocks(seed=2)
    objective = functools.partial(logdet_objective, per_view, h_train, lam)
    single = [objective([v]) for v in range(8)]
    gain = functools.partial(dopt_gain if kind == "diagonal" else block_logdet_gain, lam=lam)
    picked, first = greedy_joint(gain, per_view, h_train, 1)
    assert picked == [max(range(8), key=single.__getitem__)]
    assert first.tolist() == pytest.approx(single, rel=1e-10)


def test_block_gain_of_one_by_one_blocks_is_dopt_and_float32_keeps_small_gains():
    per_view, h_train, lam = random_diagonals(3)
    as_blocks = block_logdet_gain(per_view[:, :, None, None], h_train[:, None, None], lam[:1])
    assert as_blocks.tolist() == pytest.approx(dopt_gain(per_view, h_train, 0.05).tolist(), rel=1e-12)
    # Little information on top of a large, ill-conditioned H_train (as on a GPU, in float32): logdet(I + L^-1 B L^-T)
    # keeps it, where the difference of the two log-dets loses it.
    b, a, lam = random_blocks(seed=4)
    b, a = 1e-4 * b, 1e3 * a
    exact = block_logdet_gain(b, a, lam)
    single = block_logdet_gain(b.float(), a.float(), lam.float()).double()
    both = (a + torch.diag(lam)).float()
    naive = (torch.linalg.slogdet(both + b.float())[1] - torch.linalg.slogdet(both)[1]).sum(-1).double()
    assert float(exact.min()) > 1e-3
    assert float(((single - exact) / exact).abs().max()) < 1e-3 < float(((naive - exact) / exact).abs().max())


def test_the_selectors_picks_are_greedy_joint_on_the_brute_force_hessians(scene):
    """`views-per-round 3` under `dopt-block`: the selector's picks (each pick's exact Hessian joins H_train, lambda
    the round's) are `greedy_joint`'s on the brute-force Hessians, the SH rest as a diagonal part of each block."""
    splat, cams, blocks = scene
    active, pool = [0], [1, 2, 3, 4]
    selection = FisherSelectorConfig(criterion="dopt-block", mode="exact", resolution_scale=1.0).setup().select(
        context(splat, cams, active, pool, k=3))
    cols = columns(splat)
    rows = torch.cat([torch.arange(cols[n].start, cols[n].stop) for n in BLOCK])
    rest = torch.arange(cols["features_rest"].start, cols["features_rest"].stop)

    def embed(b):  # [N, P, P] full blocks -> [N, 19, 19]: the 10 block rows, then the rest's 9 diagonal entries
        out = torch.zeros(b.shape[0], 19, 19, dtype=b.dtype)
        out[:, :10, :10] = b[:, rows][:, :, rows]
        out[:, 10:, 10:] = torch.diag_embed(b.diagonal(dim1=-2, dim2=-1)[:, rest])
        return out

    per_view, h_train = torch.stack([embed(blocks[v]) for v in pool]), embed(blocks[0])
    diag_train = blocks[0].diagonal(dim1=-2, dim2=-1)
    lam = torch.cat([torch.full((cols[n].stop - cols[n].start,), 1e-6 + 1e-2 * float(diag_train[:, cols[n]].mean()),
                                dtype=torch.float64) for n in BLOCK + ("features_rest",)])
    picked, first = greedy_joint(functools.partial(block_logdet_gain, lam=lam), per_view, h_train, 3)
    assert selection.indices == [pool[i] for i in picked]
    assert [selection.scores[c] for c in pool] == pytest.approx(first.tolist(), rel=1e-9)
    assert selection.indices != sorted(pool, key=lambda c: -selection.scores[c])[:3]  # joint, not the top 3 singles


# ---- 3. `trace` is FisherRF's formula, as before -------------------------------------------------------------------


def test_trace_scores_and_picks_are_fisherrfs_formula_on_the_same_probe_diagonals(scene):
    """Default options (probes, half resolution, two views): the scores are sum_i h_c / (H_train + lambda) of the
    probe diagonals the selector draws, and the second pick sees the first's diagonal in H_train."""
    splat, cams, _ = scene
    selector = FisherSelectorConfig().setup()
    ctx = context(splat, cams, ACTIVE, CANDIDATES, k=2, seed=3)
    selection = selector.select(ctx)
    # The same probes in the same order: the selector's generator, seeded from the round's.
    generator = torch.Generator().manual_seed(int(torch.randint(0, 2**62, (1,), generator=torch.Generator().manual_seed(3))))
    names = ORDER[:5]

    def per_view_diagonals(views, probes):
        out = {v: {n: torch.zeros_like(splat.params[n]) for n in names} for v in views}
        for batch in selector.batches(ctx, views):
            pr = selector.render(ctx, splat, batch)
            squares = selector.pair_squares(pr, probes, generator)
            for i, v in enumerate(batch.views):
                mine = pr.camera_ids == i
                for n in names:
                    out[v][n].index_add_(0, pr.gaussian_ids[mine], squares[n][mine])
        return out

    def scores(pool, h_train):
        h_c = per_view_diagonals(pool, 16)
        lam = {n: 1e-6 + 1e-2 * float(h_train[n].mean()) for n in names}
        return {c: sum(float((h_c[c][n] / (h_train[n] + lam[n])).sum()) for n in names) for c in pool}

    train_views = per_view_diagonals(ACTIVE, 64)
    h_train = {n: sum(train_views[v][n] for v in ACTIVE) for n in names}
    first = scores(CANDIDATES, h_train)
    best = max(first, key=first.get)
    pick = per_view_diagonals([best], 64)[best]
    h_train = {n: h_train[n] + pick[n] for n in names}
    second = scores([c for c in CANDIDATES if c != best], h_train)
    assert [selection.scores[c] for c in CANDIDATES] == pytest.approx([first[c] for c in CANDIDATES], rel=1e-12)
    assert selection.indices == [best, max(second, key=second.get)]


# ---- 4. an unknown criterion ---------------------------------------------------------------------------------------


MESSAGE = "--pipeline.selection.fisher.criterion x: unknown criterion; choose trace, dopt or dopt-block"


def test_an_unknown_criterion_is_one_line_in_code_and_on_the_command_line():
    from hpgs_ns.selection.config import SelectionConfig

    with pytest.raises(OptionError) as info:
        FisherSelectorConfig(criterion="x")
    assert str(info.value) == MESSAGE
    # As ns-train parses --pipeline.selection.* (the selection group alone: the same nesting, seconds less)
    with pytest.raises(OptionError) as info:
        tyro.cli(SelectionConfig, args=["--selector", "fisher", "--fisher.criterion", "x"])
    assert str(info.value) == MESSAGE and not isinstance(info.value, ValueError)  # tyro would draw its box
    assert tyro.cli(SelectionConfig, args=["--fisher.criterion", "dopt-block"]).fisher.criterion == "dopt-block"
    assert FisherSelectorConfig().criterion == "trace"
    config = FisherSelectorConfig()
    config.criterion = "x"  # set after it was built: the selector checks it too
    with pytest.raises(OptionError, match="^" + MESSAGE.replace("(", r"\(") + "$"):
        config.setup()
