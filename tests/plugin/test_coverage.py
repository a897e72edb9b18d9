"""The `coverage` selector: per-pair max T*alpha weights (against explicit compositing), the direction table, the
uncovered-share score, greedy batches and its option errors."""

from __future__ import annotations

import contextlib
import math

import pytest
import torch
import tyro
from nerfstudio.cameras.cameras import Cameras

from hpgs_ns.errors import OptionError
from hpgs_ns.method_config import hpgs_trainer_config
from hpgs_ns.render.coverage import max_weights, project_visible, render_values
from hpgs_ns.render.pair_render import Splat
from hpgs_ns.selectors.base import SelectionContext, check_selection
from hpgs_ns.selectors.coverage import CoverageSelectorConfig, fibonacci_sphere
from hpgs_ns.selectors.farthest import nearest_centre_distance

torch.set_num_threads(1)


def gaussians(means, scales, opacities) -> dict:
    """Round Gaussians (raw parameters as splatfacto stores them): means [N, 3], scales [N] (linear), opacities [N]
    (probabilities)."""
    means = torch.as_tensor(means, dtype=torch.float64).reshape(-1, 3)
    n = means.shape[0]
    scales = torch.as_tensor(scales, dtype=torch.float64).reshape(n, 1).expand(n, 3)
    opacities = torch.as_tensor(opacities, dtype=torch.float64).reshape(n, 1)
    return {"means": means, "quats": torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4).clone(),
            "scales": scales.log(), "opacities": torch.logit(opacities), "features_dc": torch.zeros(n, 3, dtype=torch.float64),
            "features_rest": torch.zeros(n, 0, 3, dtype=torch.float64)}


def as_splat(params: dict, backend: str = "cpu") -> Splat:
    return Splat(params=params, sh_degree=None, background=torch.zeros(3, dtype=params["means"].dtype), backend=backend)


def looking_down_z(n: int = 1, f: float = 40.0, width: int = 32, height: int = 32):
    """n identity cameras (OpenCV: looking along +z from the origin), principal point on a pixel centre."""
    K = torch.tensor([[f, 0, width / 2 + 0.5], [0, f, height / 2 + 0.5], [0, 0, 1]], dtype=torch.float64)
    return torch.eye(4, dtype=torch.float64).expand(n, 4, 4).contiguous(), K.expand(n, 3, 3).contiguous(), width, height


def test_a_gaussian_behind_an_opaque_one_is_barely_covered_and_a_lone_one_gets_its_opacity():
    viewmats, Ks, W, H = looking_down_z()
    # Same ray from the camera: an opaque wide Gaussian at depth 2, a small one behind it at depth 4.
    params = gaussians([[0, 0, 2.0], [0, 0, 4.0]], [0.5, 0.1], [0.9975, 0.9])
    pairs = project_visible(as_splat(params), viewmats, Ks, W, H)
    w = dict(zip(pairs.gaussian_ids.tolist(), max_weights(pairs).tolist()))
    assert w[0] == pytest.approx(0.9975, abs=1e-9)  # centred on a pixel centre: alpha = its opacity, T = 1
    assert 0 < w[1] < 0.05 * w[0]
    # Alone, the back one is in full view: its weight is its opacity (its largest alpha, at the centre pixel).
    lone = project_visible(as_splat(gaussians([[0, 0, 4.0]], [0.1], [0.9])), viewmats, Ks, W, H)
    assert max_weights(lone).tolist() == pytest.approx([0.9], abs=1e-9)


def brute_force(pairs, values):
    """Per pixel, front to back, gsplat's rules written out: alpha = min(0.999, o exp(-sigma)), skipped where
    sigma < 0 or alpha < 1/255, stop before T would reach 1e-4. -> (max weight per pair [nnz], image [C, H, W],
    how many pixels stopped)."""
    best = torch.zeros(pairs.camera_ids.numel(), dtype=torch.float64)
    image = torch.zeros(pairs.n_cameras, pairs.height, pairs.width, dtype=torch.float64)
    stops = 0
    for c in range(pairs.n_cameras):
        mine = [int(k) for k in torch.nonzero(pairs.camera_ids == c).flatten()]
        mine.sort(key=lambda k: float(pairs.depths[k]))
        for y in range(pairs.height):
            for x in range(pairs.width):
                T, colour = 1.0, 0.0
                for k in mine:
                    dx, dy = (pairs.means2d[k] - torch.tensor([x + 0.5, y + 0.5], dtype=torch.float64)).tolist()
                    a, b, cc = pairs.conics[k].tolist()
                    sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
                    alpha = min(0.999, float(pairs.opacities[k]) * math.exp(-sigma))
                    if sigma < 0 or alpha < 1 / 255:
                        continue
                    if T * (1 - alpha) <= 1e-4:
                        stops += 1
                        break
                    best[k] = max(best[k], T * alpha)
                    colour += T * alpha * float(values[k])
                    T *= 1 - alpha
                image[c, y, x] = colour + T
    return best, image, stops


def test_max_weights_and_the_value_image_equal_explicit_front_to_back_compositing():
    g = torch.Generator().manual_seed(0)
    # Three wide opaque ones in front (the centre pixels stop on them), one behind, one below 1/255 everywhere.
    means = [[0.0, 0.0, 1.0], [0.05, 0.0, 1.2], [-0.05, 0.03, 1.4], [0.2, -0.1, 3.0], [-0.2, 0.1, 2.5]]
    params = gaussians(means, [0.5, 0.5, 0.5, 0.3, 0.4], [0.9999, 0.9999, 0.9999, 0.7, 0.003])
    params["quats"] = torch.randn(5, 4, generator=g, dtype=torch.float64)  # anisotropic, rotated
    params["scales"] = params["scales"] + torch.tensor([0.0, -0.4, -0.8], dtype=torch.float64)
    viewmats, Ks, W, H = looking_down_z(2, f=8.0, width=8, height=6)
    viewmats[1, :3, 3] = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)  # a second, shifted view
    pairs = project_visible(as_splat(params), viewmats, Ks, W, H)
    values = torch.rand(pairs.camera_ids.numel(), generator=g, dtype=torch.float64)
    best, image, stops = brute_force(pairs, values)
    assert pairs.camera_ids.numel() == 10 and stops > 0 and (best == 0).sum() == 2  # the faint one gets nothing
    assert torch.allclose(max_weights(pairs), best, rtol=0, atol=1e-12)
    assert torch.allclose(render_values(pairs, values), image, rtol=0, atol=1e-12)


# ---- the selector on a ring of cameras around a ball of Gaussians -------------------------------------------------


def camera_to_world(centre, look_at=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """[3, 4] nerfstudio (OpenGL) pose at `centre` looking at `look_at`, z up."""
    centre = torch.as_tensor(centre, dtype=torch.float32)
    back = centre - torch.as_tensor(look_at, dtype=torch.float32)
    back = back / back.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back)
    right = right / right.norm()
    return torch.stack([right, torch.linalg.cross(back, right), back, centre], dim=1)


def ring(n: int = 24, extra=()) -> Cameras:
    """n cameras on a circle of radius 3 around the origin, looking at it, then the poses `extra`."""
    c2w = [camera_to_world((3 * math.cos(2 * math.pi * k / n), 3 * math.sin(2 * math.pi * k / n), 0.0)) for k in range(n)]
    return Cameras(camera_to_worlds=torch.stack(c2w + list(extra)), fx=80.0, fy=80.0, cx=16.0, cy=16.0, width=32, height=32)


class Ball:
    """Stands in for the model: `splat()` and `eval_mode()`, a shell of opaque Gaussians of radius 0.5."""

    def __init__(self, n: int = 300) -> None:
        self.params = gaussians(fibonacci_sphere(n, torch.float64) * 0.5, [0.07] * n, [0.95] * n)

    @contextlib.contextmanager
    def eval_mode(self):
        yield self

    def splat(self) -> Splat:
        return as_splat(self.params)


def context(cameras: Cameras, active, candidates, k: int = 1) -> SelectionContext:
    return SelectionContext(
        step=0, round_index=0, active=list(active), candidates=list(candidates), num_to_pick=k, cameras=cameras,
        image_names=[f"{i:03d}.png" for i in range(len(cameras))], model=Ball(), render=None,  # type: ignore[arg-type]
        generator=torch.Generator().manual_seed(0),
    )


ACTIVE = [22, 23, 0, 1, 2]  # one side of the ring, around +x


def test_empty_view_scores_one_an_active_pose_scores_low_and_the_pick_is_on_the_far_side():
    away = camera_to_world((3.0, 0.0, 0.0), look_at=(6.0, 0.0, 0.0))  # at camera 0, looking away from the ball
    cameras = ring(extra=[away, camera_to_world((3.0, 0.0, 0.0))])  # 24: sees nothing; 25: camera 0's pose
    candidates = [i for i in range(26) if i not in ACTIVE]
    ctx = context(cameras, ACTIVE, candidates)
    selection = check_selection(CoverageSelectorConfig().setup().select(ctx), ctx)
    scores = selection.scores
    assert scores[24] == 1.0  # nothing seen: every pixel is background, all uncovered
    assert scores[25] < 0.6 < scores[12]  # the ball's face camera 0 covers (and 45% background) vs its back
    assert scores[12] == pytest.approx(1.0, abs=1e-6)
    picked = selection.indices[0]
    centre = cameras.camera_to_worlds[picked, :3, 3]
    assert float(centre[0]) < -2.5  # on the far side (camera 12 sits at x = -3)
    # Neighbours of the active arc see part of the covered face from nearby directions.
    assert max(scores[3], scores[21]) < 1.0 - 1e-3
    assert selection.work["views_rendered"] == len(ACTIVE) + len(candidates)
    assert selection.work["pixels_rendered"] * 4 == selection.work["pixels_full_resolution"]  # resolution-scale 0.5


def test_greedy_second_pick_sees_the_first_picks_directions_as_covered():
    candidates = [i for i in range(24) if i not in ACTIVE]
    selector = CoverageSelectorConfig().setup()
    two = selector.select(context(ring(), ACTIVE, candidates, k=2))
    first, second = two.indices
    assert first == 12 and second != first
    # Brute-force greedy: the first pick made active, the same selector asked again for one view.
    again = selector.select(context(ring(), ACTIVE + [first], [c for c in candidates if c != first]))
    assert again.indices == [second]
    # The first pick's weights joined the table: its neighbours, fully uncovered before it, are partly covered now.
    assert two.scores[11] == two.scores[13] == pytest.approx(1.0, abs=1e-6)
    assert max(again.scores[11], again.scores[13]) < 1.0 - 1e-3
    # The first pass's ranking alone (ties to the farthest from the active views) would take a neighbour of the pick.
    tied = [c for c in candidates if c != first and two.scores[c] >= max(two.scores.values()) - 1e-3]
    naive = tied[int(nearest_centre_distance(ring(), tied, ACTIVE).argmax())]
    assert naive in (11, 13) and second not in (11, 13)
    # Only the candidates that read an entry the pick changed were rendered again: at least those whose score moved.
    moved = sum(abs(again.scores[c] - two.scores[c]) > 1e-12 for c in again.scores)
    assert len(ACTIVE) + len(candidates) + 1 + moved <= two.work["views_rendered"] < len(ACTIVE) + 2 * len(candidates)


BAD = [
    (["--pipeline.selection.coverage.bins", "0"], "--pipeline.selection.coverage.bins 0: must be at least 1; 32 is the default"),
    (["--pipeline.selection.coverage.resolution-scale", "0"],
     "--pipeline.selection.coverage.resolution-scale 0.0: must be in (0, 1]; 0.5 renders at half the dataset resolution"),
    (["--pipeline.selection.coverage.view-batch", "0"],
     "--pipeline.selection.coverage.view-batch 0: must be at least 1; lower it if GPU memory runs out"),
]


@pytest.mark.parametrize("args, line", BAD, ids=[row[0][0] for row in BAD])
def test_a_bad_option_value_is_its_one_line(args, line):
    default = hpgs_trainer_config(100)
    with pytest.raises(OptionError) as info:
        tyro.cli(type(default), default=default, args=["--pipeline.selection.selector", "coverage"] + args)
    assert str(info.value) == line


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (gsplat's kernels)")
def test_gsplat_backend_matches_the_cpu_twin():
    g = torch.Generator().manual_seed(1)
    n = 2000
    params = gaussians(torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.6, torch.rand(n, generator=g) * 0.08 + 0.02,
                       torch.rand(n, generator=g) * 0.98 + 0.01)
    params = {k: v.float().cuda() for k, v in params.items()}
    cameras = ring(6)
    from hpgs_ns.render.viewmats import world_to_camera

    viewmats = world_to_camera(cameras.camera_to_worlds).cuda()
    Ks = cameras.get_intrinsics_matrices().cuda()
    out = {}
    for backend in ("gsplat", "cpu"):
        pairs = project_visible(as_splat(params, backend), viewmats, Ks, 32, 32)
        values = torch.rand(pairs.camera_ids.numel(), generator=torch.Generator().manual_seed(2)).cuda()
        out[backend] = (pairs.camera_ids, max_weights(pairs), render_values(pairs, values))
    assert torch.equal(out["gsplat"][0], out["cpu"][0])
    assert (out["gsplat"][1] - out["cpu"][1]).abs().max() < 1e-4
    assert (out["gsplat"][2] - out["cpu"][2]).abs().max() < 1e-4
