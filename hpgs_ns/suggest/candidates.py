"""Camera poses without photos, in nerfstudio's (the dataparser's) coordinates, and the filters that drop the
unusable ones. Poses are [N, 3, 4] camera-to-world matrices in nerfstudio's convention (x right, y up, the camera
looking along -z)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import torch

from hpgs_ns.errors import UserError


class CandidateError(UserError, ValueError):
    """Candidate poses cannot be made or read, or none is left after filtering."""


@dataclass
class Layout:
    """Where a capture's cameras are, around what."""

    centre: torch.Tensor
    """[3] the point the cameras look at (least-squares meeting point of their viewing rays)."""
    up: torch.Tensor
    """[3] unit vector: the mean of the cameras' up directions."""
    heights: torch.Tensor
    """[N] each captured camera's height above the centre along `up`."""
    radii: torch.Tensor
    """[N] each captured camera's distance from the up axis through the centre."""
    spacing: float
    """Median distance from a captured camera to its nearest neighbour."""


def layout(c2w: torch.Tensor) -> Layout:
    """The layout of captured cameras c2w [N, 3, 4]."""
    c2w = c2w.double()
    centres, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    # argmin_p sum_i |(I - d_i d_i^T)(p - o_i)|^2: the point nearest to every viewing ray
    projector = torch.eye(3, dtype=c2w.dtype) - forward[:, :, None] * forward[:, None, :]
    centre = torch.linalg.lstsq(projector.sum(0), (projector @ centres[:, :, None]).sum(0)).solution[:, 0]
    if not torch.isfinite(centre).all() or (centre - centres.mean(0)).norm() > 10 * (centres - centres.mean(0)).norm(dim=1).max():
        centre = centres.mean(0)  # parallel rays (a forward-facing capture): their centroid
    up = c2w[:, :3, 1].mean(0)
    up = up / up.norm().clamp_min(1e-12)
    rel = centres - centre
    heights = rel @ up
    radii = (rel - heights[:, None] * up).norm(dim=1)
    dist = torch.cdist(centres, centres) + torch.eye(len(centres), dtype=c2w.dtype) * 1e30
    spacing = float(dist.min(dim=1).values.median()) if len(centres) > 1 else 1.0
    return Layout(centre.float(), up.float(), heights.float(), radii.float(), spacing)


def look_at(eyes: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """c2w [N, 3, 4] of cameras at `eyes` [N, 3] looking at `target` [3], rolled so that `up` is up."""
    forward = torch.nn.functional.normalize(target[None] - eyes, dim=-1)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up.expand_as(forward), dim=-1), dim=-1)
    cam_up = torch.linalg.cross(right, forward, dim=-1)
    rotation = torch.stack([right, cam_up, -forward], dim=-1)
    return torch.cat([rotation, eyes[:, :, None]], dim=-1)


def orbit(lay: Layout, rings: int = 3, per_ring: int = 36) -> torch.Tensor:
    """Rings around the centre at the heights of the captured cameras (lowest to highest) and, for each, the
    median radius of the cameras nearest that height; every camera looks at the centre."""
    levels = torch.quantile(lay.heights, torch.linspace(0, 1, rings)) if rings > 1 else lay.heights.median()[None]
    u = lay.up
    side = torch.tensor([1.0, 0, 0]) if abs(u[0]) < 0.9 else torch.tensor([0, 1.0, 0])
    a = torch.nn.functional.normalize(torch.linalg.cross(u, side, dim=0), dim=0)
    b = torch.linalg.cross(u, a, dim=0)
    eyes = []
    for h in levels:
        near = (lay.heights - h).abs().argsort()[: max(3, len(lay.heights) // rings)]
        r = lay.radii[near].median()
        for k in range(per_ring):
            t = 2 * math.pi * k / per_ring
            eyes.append(lay.centre + h * u + r * (math.cos(t) * a + math.sin(t) * b))
    return look_at(torch.stack(eyes), lay.centre, u)


def sphere(lay: Layout, count: int = 128) -> torch.Tensor:
    """A Fibonacci sphere of `count` viewpoints around the centre, at the median distance of the captured
    cameras, looking at the centre."""
    radius = float(torch.sqrt(lay.radii**2 + lay.heights**2).median())
    k = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / count
    phi = math.pi * (1 + 5**0.5) * k
    dirs = torch.stack([torch.sqrt(1 - z**2) * torch.cos(phi), torch.sqrt(1 - z**2) * torch.sin(phi), z], -1).float()
    # the sphere's pole on `up`, so its rings follow the capture's ground plane
    u = lay.up
    side = torch.tensor([1.0, 0, 0]) if abs(u[0]) < 0.9 else torch.tensor([0, 1.0, 0])
    a = torch.nn.functional.normalize(torch.linalg.cross(u, side, dim=0), dim=0)
    basis = torch.stack([a, torch.linalg.cross(u, a, dim=0), u], 0)
    eyes = lay.centre + radius * dirs @ basis
    up = u.clone()
    poles = (dirs[:, 2].abs() > 0.999)
    if poles.any():  # straight above or below: "up" is undefined, use the sphere's `a` axis
        up = torch.where(poles[:, None], a.expand(count, 3), u.expand(count, 3))
        return torch.stack([look_at(e[None], lay.centre, v)[0] for e, v in zip(eyes, up)])
    return look_at(eyes, lay.centre, u)


def from_file(path: Path) -> Tuple[torch.Tensor, List[float]]:
    """(c2w [N, 3, 4], vertical fov in degrees or nan each) from a nerfstudio camera-path JSON (what the viewer's
    render panel exports: `camera_path`, or its `keyframes`) or a JSON list of 4x4 / 3x4 matrices or of
    {"camera_to_world": ..., "fov": ...}; nerfstudio coordinates and camera convention, as the viewer's."""
    try:
        data = json.loads(Path(path).read_text())
        if isinstance(data, dict):
            entries = data.get("camera_path") or [{"camera_to_world": k["matrix"], "fov": k.get("fov")} for k in data["keyframes"]]
        else:
            entries = [e if isinstance(e, dict) else {"camera_to_world": e} for e in data]
        poses, fovs = [], []
        for e in entries:
            m = torch.tensor(e["camera_to_world"], dtype=torch.float32).reshape(-1)
            if m.numel() not in (12, 16):
                raise ValueError(f"a pose has {m.numel()} numbers, not 12 or 16")
            poses.append(m.reshape(-1, 4)[:3])
            fovs.append(float(e["fov"]) if e.get("fov") is not None else float("nan"))
        if not poses:
            raise ValueError("no poses")
        return torch.stack(poses), fovs
    except (OSError, ValueError, KeyError, TypeError, RuntimeError) as err:
        raise CandidateError(
            f"{path} is not a camera path ({err}); pass a nerfstudio camera-path JSON (the viewer's render panel "
            "exports one) or a JSON list of 4x4 camera-to-world matrices"
        ) from None


def too_close(c2w: torch.Tensor, captured: torch.Tensor, distance: float) -> torch.Tensor:
    """[N] bool: centres within `distance` of a captured camera's centre."""
    return torch.cdist(c2w[:, :3, 3].double(), captured[:, :3, 3].double()).min(dim=1).values < distance


def inside_object(c2w: torch.Tensor, means: torch.Tensor, opacities: torch.Tensor, lay: Layout) -> torch.Tensor:
    """[N] bool: centres inside the bounding box of the opaque Gaussians around the centre (those nearer to it
    than 90% of the closest captured camera: the object a capture goes around, not the walls behind it)."""
    reach = 0.9 * float(torch.sqrt(lay.radii**2 + lay.heights**2).min())
    keep = (opacities > 0.5) & ((means - lay.centre).norm(dim=1) < reach)
    if keep.sum() < 10:
        return torch.zeros(len(c2w), dtype=torch.bool)
    lo, hi = means[keep].min(0).values, means[keep].max(0).values
    centres = c2w[:, :3, 3]
    return ((centres >= lo) & (centres <= hi)).all(dim=1)


def counts(**masks: torch.Tensor) -> Dict[str, int]:
    return {name: int(mask.sum()) for name, mask in masks.items()}
