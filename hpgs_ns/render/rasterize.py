"""How splatfacto turns its stored Gaussians into an image, written once.

The rasterizer's settings, the activations of splatfacto's raw parameters and the background/clamp rule, as
nerfstudio 1.1.5's `SplatfactoModel.get_outputs` has them. `HpgsSplatfactoModel._rasterize_cameras` (training,
eval and selection renders) and `pair_render` (FisherRF's per-pair renders) both read them from here;
a CPU test pins the model's renders to stock splatfacto's.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import torch
from torch import Tensor

NEAR_PLANE = 0.01  # splatfacto's
FAR_PLANE = 1e10  # splatfacto's
EPS2D = 0.3  # gsplat's default low-pass (splatfacto keeps it)
TILE_SIZE = 16  # gsplat's default (splatfacto keeps it)


def splat_opacities(raw: Tensor) -> Tensor:
    """Splatfacto's opacity: raw logits [N, 1] -> [N] in (0, 1)."""
    return torch.sigmoid(raw).squeeze(-1)


def splat_colors(features_dc: Tensor, features_rest: Tensor, sh_degree: Optional[int]) -> Tensor:
    """What splatfacto hands the rasterizer as colours: SH coefficients [N, K, 3] (rasterized at `sh_degree`), or,
    when `sh_degree` is None (a model without SH), sigmoid RGB [N, 3]. features_dc [N, 3], features_rest
    [N, K - 1, 3]."""
    coeffs = torch.cat((features_dc[:, None, :], features_rest), dim=1)
    return coeffs if sh_degree is not None else torch.sigmoid(coeffs).squeeze(1)


def composite(render: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    """Splatfacto's image: the rendered colour [..., H, W, 3] over `background` [3] by the alpha [..., H, W, 1],
    clamped to [0, 1]."""
    return torch.clamp(render + (1 - alpha) * background, 0.0, 1.0)


def rasterize_splat(
    rasterize: Callable,
    params: Dict[str, Tensor],
    sh_degree: Optional[int],
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    rasterize_mode: str = "classic",
    render_mode: str = "RGB",
    absgrad: bool = False,
) -> Tuple[Tensor, Tensor, Dict]:
    """Splatfacto's rasterization call: raw Gaussians `params` (means [N, 3], quats [N, 4], scales [N, 3] (log),
    opacities [N, 1] (logit), features_dc [N, 3], features_rest [N, K - 1, 3]) seen from C cameras (viewmats
    [C, 4, 4] world-to-camera, Ks [C, 3, 3]) by `rasterize` (gsplat's `rasterization` or `cpu_raster`'s).

    Returns gsplat's (render [C, H, W, X], alpha [C, H, W, 1], info), not composited."""
    return rasterize(
        means=params["means"],
        quats=params["quats"],  # the rasterizer normalizes them
        scales=torch.exp(params["scales"]),
        opacities=splat_opacities(params["opacities"]),
        colors=splat_colors(params["features_dc"], params["features_rest"], sh_degree),
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
        near_plane=NEAR_PLANE,
        far_plane=FAR_PLANE,
        eps2d=EPS2D,
        tile_size=TILE_SIZE,
        packed=False,  # splatfacto's layout: the densification strategy reads info["means2d"] as [C, N, 2]
        render_mode=render_mode,
        sh_degree=sh_degree,
        sparse_grad=False,
        absgrad=absgrad,
        rasterize_mode=rasterize_mode,
    )
