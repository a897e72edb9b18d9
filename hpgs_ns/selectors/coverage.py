"""`coverage`: the candidate that sees the most surface the training views have not covered from its direction.

After COVER / NBV-Gym (CVPR 2026), which scores views by the uncovered surface they would see, with each Gaussian's
coverage weighted by its transmittance times opacity as in PRIMU-AVS.

A Gaussian g's weight from a view c is the largest compositing weight it gets over c's pixels,

    w_gc = max_p T_g(p) alpha_g(p),

so a Gaussian hidden behind an opaque one is barely covered (`render.coverage.max_weights`). Each Gaussian keeps a
table over B direction bins (a Fibonacci sphere; the direction from its centre to the camera centre):

    coverage[g, b] = 1 - prod over active views c in bin b of (1 - w_gc).

A candidate v is scored by rendering each Gaussian's uncovered value u_gv = 1 - coverage[g, bin(g -> v)] as its
colour over a background of 1 (an empty pixel is all uncovered) and taking the image mean:

    score(v) = mean over pixels of [sum_g T alpha u_gv + T_final].

A candidate that sees nothing scores exactly 1, and so does any view of surface no active view saw from its
direction; among scores within `tie_tolerance` of the best, the camera farthest from the active ones wins (`farthest`'s
score). With several views a round, each pick's weights join the table before the next pick, and only the candidates
that read a table entry the pick changed are rendered again. Views are rendered at `resolution_scale` of the dataset
resolution, `view_batch` at a time, with the model's rasterizer (gsplat's kernels on a GPU, `cpu_raster` on the CPU).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Dict, Iterator, List, Optional, Sequence, Tuple, Type

import torch
from torch import Tensor

from hpgs_ns.errors import check_option
from hpgs_ns.render.coverage import ProjectedPairs, max_weights, project_visible, render_values
from hpgs_ns.render.pair_render import Splat
from hpgs_ns.render.viewmats import ViewBatch, view_batches
from hpgs_ns.selectors.base import Selection, SelectionContext, SelectorConfig
from hpgs_ns.selectors.farthest import nearest_centre_distance

BIN_ROWS_PER_CHUNK = 1 << 20  # pairs binned at once (a [rows, bins] product: bounds memory, not results)
FLAG = "--pipeline.selection.coverage."


@dataclass
class CoverageSelectorConfig(SelectorConfig):
    """Direction-aware coverage of the splat's Gaussians by the training views, weighted by transmittance x alpha
    (COVER / NBV-Gym, CVPR 2026; the weighting of PRIMU-AVS): the candidate that sees the most uncovered surface."""

    _target: Type = field(default_factory=lambda: CoverageSelector)
    code_files: ClassVar[Tuple[str, ...]] = ("render/coverage.py", "render/pair_render.py")
    bins: int = 32
    """Direction bins per Gaussian (points of a Fibonacci sphere; 32 bins are cones of about 20 degrees half-angle).
    The table holds this many numbers per Gaussian."""
    resolution_scale: float = 0.5
    """Render views at this fraction of the dataset resolution (halving the side quarters the cost)."""
    view_batch: int = 32
    """Views rendered together in one rasterization call (memory grows with it; lower it if GPU memory runs out)."""
    tie_tolerance: float = 1e-3
    """Scores within this of the best count as ties (every view that sees only uncovered surface scores 1); among
    them the camera centre farthest from the active ones wins, as `farthest` picks."""

    def __post_init__(self) -> None:
        check_option(FLAG + "bins", self.bins, self.bins >= 1, "must be at least 1", "32 is the default")
        check_option(FLAG + "resolution-scale", self.resolution_scale, 0 < self.resolution_scale <= 1,
                     "must be in (0, 1]", "0.5 renders at half the dataset resolution")
        check_option(FLAG + "view-batch", self.view_batch, self.view_batch >= 1, "must be at least 1",
                     "lower it if GPU memory runs out")
        check_option(FLAG + "tie-tolerance", self.tie_tolerance, 0 <= self.tie_tolerance < 1, "must be in [0, 1)",
                     "0 takes the highest score alone")



def fibonacci_sphere(n: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """[n, 3] unit vectors spread evenly over the sphere (the golden-angle spiral)."""
    k = torch.arange(n, dtype=torch.float64, device=device)
    z = 1.0 - (2.0 * k + 1.0) / n
    r = torch.sqrt(torch.clamp_min(1.0 - z * z, 0.0))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1).to(dtype)


def direction_bins(directions: Tensor, centres: Tensor) -> Tensor:
    """[M] the bin (nearest of `centres` [B, 3], unit) of each direction [M, 3] (need not be unit)."""
    out = torch.empty(directions.shape[0], dtype=torch.long, device=directions.device)
    for start in range(0, directions.shape[0], BIN_ROWS_PER_CHUNK):
        rows = slice(start, start + BIN_ROWS_PER_CHUNK)
        out[rows] = torch.argmax(directions[rows] @ centres.T, dim=1)
    return out


def pair_bins(splat: Splat, pairs: ProjectedPairs, viewmats: Tensor, centres: Tensor) -> Tensor:
    """[nnz] the bin of the direction from each pair's Gaussian centre to its view's camera centre."""
    campos = torch.inverse(viewmats)[:, :3, 3]
    directions = campos[pairs.camera_ids] - splat.params["means"][pairs.gaussian_ids]
    return direction_bins(directions.to(centres), centres)


class CoverageTable:
    """Per Gaussian and direction bin, log prod (1 - w) over the views added: log(1 - coverage), [N, B]."""

    def __init__(self, num_gaussians: int, bins: int, dtype: torch.dtype, device) -> None:
        self.bins = bins
        self.log_uncovered = torch.zeros(num_gaussians, bins, dtype=dtype, device=device)

    def entries(self, gaussian_ids: Tensor, bins: Tensor) -> Tensor:
        """[nnz] the flat table entry of each (Gaussian, bin)."""
        return gaussian_ids * self.bins + bins

    def add(self, entries: Tensor, weights: Tensor) -> None:
        """Fold in one weight per entry ([nnz] each). A product of (1 - w) rather than the largest w: two views that
        each half-see a Gaussian from one direction show it better together than either alone."""
        # w <= 0.999 (gsplat's alpha clamp, times T <= 1): the logarithm stays finite.
        self.log_uncovered.view(-1).index_add_(0, entries, torch.log1p(-weights.to(self.log_uncovered)))

    def uncovered(self, entries: Tensor) -> Tensor:
        """[nnz] 1 - coverage of each entry."""
        return torch.exp(self.log_uncovered.view(-1)[entries])


class CoverageSelector:
    """Greedy coverage selection; each pick joins the table before the next."""

    def __init__(self, config: CoverageSelectorConfig) -> None:
        self.config = config
        self.work: Dict[str, float] = {}

    def batches(self, context: SelectionContext, views: Sequence[int], like: Tensor) -> Iterator[ViewBatch]:
        """`views` grouped by rendered size, at most `view_batch` per group, with their matrices in the dtype and on
        the device of `like`."""
        return view_batches(context.cameras, views, self.config.resolution_scale, self.config.view_batch, like)

    def project(self, context: SelectionContext, splat: Splat, batch: ViewBatch) -> ProjectedPairs:
        pairs = project_visible(splat, batch.viewmats, batch.Ks, batch.width, batch.height)
        full = context.cameras[torch.tensor(batch.views, dtype=torch.long)]
        for key, n in (("views_rendered", len(batch.views)), ("pixels_rendered", len(batch.views) * batch.width * batch.height),
                       ("pixels_full_resolution", int((full.width * full.height).sum())),
                       ("pairs_in_frustum", pairs.camera_ids.numel())):
            self.work[key] = self.work.get(key, 0) + n
        return pairs

    def cover(self, context: SelectionContext, splat: Splat, table: CoverageTable, centres: Tensor,
              views: Sequence[int]) -> Tensor:
        """Fold the weights of `views` into `table`; returns the entries that changed (unique)."""
        changed = []
        for batch in self.batches(context, views, splat.params["means"]) if views else ():
            pairs = self.project(context, splat, batch)
            context.progress(len(batch.views))
            entries = table.entries(pairs.gaussian_ids, pair_bins(splat, pairs, batch.viewmats, centres))
            weights = max_weights(pairs)
            table.add(entries, weights)
            changed.append(entries[weights > 0])
        return torch.unique(torch.cat(changed)) if changed else table.log_uncovered.new_zeros(0, dtype=torch.long)

    def scores(self, context: SelectionContext, splat: Splat, table: CoverageTable, centres: Tensor,
               views: Sequence[int], entries: Optional[Dict[int, Tensor]] = None) -> Dict[int, float]:
        """The mean uncovered share of each of `views`' pixels; `entries` (when given) gets each view's table
        entries (unique), the only ones its score reads."""
        scores: Dict[int, float] = {}
        for batch in self.batches(context, views, splat.params["means"]):
            pairs = self.project(context, splat, batch)
            context.progress(len(batch.views))
            seen = table.entries(pairs.gaussian_ids, pair_bins(splat, pairs, batch.viewmats, centres))
            image = render_values(pairs, table.uncovered(seen), background=1.0)
            scores.update(zip(batch.views, image.double().mean((1, 2)).tolist()))
            if entries is not None:
                entries.update({v: torch.unique(seen[pairs.camera_ids == k]) for k, v in enumerate(batch.views)})
        return scores

    def best(self, context: SelectionContext, scores: Dict[int, float], side: Sequence[int]) -> int:
        """The highest-scoring candidate; among ties (`tie_tolerance`) the one farthest from the centres of `side`."""
        top = max(scores.values())
        tied = [c for c in scores if scores[c] >= top - self.config.tie_tolerance]
        if not side:
            return tied[0]
        distance = nearest_centre_distance(context.cameras, tied, side)
        return tied[int(torch.argmax(distance))]

    @torch.no_grad()
    def select(self, context: SelectionContext) -> Selection:
        self.work = {}
        picked: List[int] = []
        entries: Dict[int, Tensor] = {}
        with context.model.eval_mode():
            splat = context.model.splat()
            means = splat.params["means"]
            centres = fibonacci_sphere(self.config.bins, means.dtype, means.device)
            # Rebuilt every round: densification renumbers the Gaussians.
            table = CoverageTable(splat.num_points, self.config.bins, means.dtype, means.device)
            self.cover(context, splat, table, centres, context.active)
            scores = self.scores(context, splat, table, centres, context.candidates,
                                 entries if context.num_to_pick > 1 else None)
            first_scores = dict(scores)
            while True:
                best = self.best(context, scores, list(context.active) + picked)
                picked.append(best)
                del scores[best]
                if len(picked) == context.num_to_pick:
                    break
                # Greedy: the pick's weights join the table, and the candidates that read an entry it changed are
                # scored again (the others' scores cannot have moved).
                changed = self.cover(context, splat, table, centres, [best])
                stale = [c for c in scores if bool(torch.isin(entries[c], changed).any())]
                if stale:
                    scores.update(self.scores(context, splat, table, centres, stale))
        return Selection(indices=picked, scores=first_scores, work=dict(self.work))

