"""The embedded synthetic scene: procedural textured objects, a 360-degree capture and exact ground truth.

Writes a folder in the Mip-NeRF 360 layout that nerfstudio's stock `colmap` dataparser loads unchanged:

    DIR/images/0000.png ...            capture order: ring by ring (lowest first), azimuth increasing
    DIR/sparse/0/{cameras,images,points3D}.bin   (+ rigs.bin, frames.bin from pycolmap 4)
    DIR/ground_truth.json               cameras, objects, which camera sees which object, hidden objects

The scene is ray cast analytically in numpy (spheres, boxes, cylinders, a ground disc and a cylindrical
backdrop, each with a checker/stripes/rings/noise texture), Lambertian shading with one directional light and
cast shadows, so every pixel's colour is view-independent and known exactly. The 3D points are samples of
visible surfaces with their true colours; each point's track lists exactly the images in which it is in the
frustum and not occluded, with a 2D keypoint at its exact projection.

Layouts: `ring` (default; objects around the centre, a wall hides the magenta sphere from the +x side),
`occluded` (the gold sphere sits in a walled pocket open towards +x: only the ~quarter of the cameras facing the
opening see it), `sparse-objects` (six small objects spread over a wide ground, no occluders).

Usage: `hpgs make-scene --layout occluded --out data/occluded` or `make_scene(path, layout="occluded", seed=0)`.
Default (48 cameras, 96x72, 4000 points) takes ~2-3 s on 2 CPU cores.

ground_truth.json: `layout`, `seed`, `spec` (all SceneSpec fields), `frame`, `up`, `target`, `light_direction`,
`intrinsics`, `cameras` (name, image_id, ring, height above the ground, azimuth_deg, center, look, `sees`: objects
covering >= `sees_min_pixels` pixels, `coverage`: fraction of the image per object), `objects` (name, kind, role,
geometry, texture, colour, `seen_by` camera names, `num_points3D`), `hidden` (the objects the layout hides from
some cameras, with `seen_by`), `limited_visibility` (objects and occluders seen by < half the cameras).

Frames: the scene is modelled with z up; the files use the COLMAP convention (world gravity along +y, so
nerfstudio's `assume_colmap_world_coordinate_convention` maps the scene's up to +z; cameras x right, y down,
z forward). Everything in ground_truth.json is in the COLMAP world frame of `sparse/0`.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np

from hpgs_ns.errors import UserError

LAYOUTS = ("ring", "occluded", "sparse-objects")
Layout = Literal["ring", "occluded", "sparse-objects"]

# Scene (z-up) -> COLMAP world (y down): (x, y, z) -> (x, -z, y). A proper rotation (det +1).
SCENE_TO_COLMAP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_EPS = 1e-6
_CHUNK = 1 << 17  # rays per numpy batch: bounds memory for large images


class SceneSpecError(UserError, ValueError):
    """A bad argument to the scene generator (message is one line, meant for the user)."""


@dataclass
class SceneSpec:
    """What to generate. Every field is a `hpgs make-scene` flag."""

    layout: Layout = "ring"
    """ring: objects around the centre, one hidden behind a wall from one side; occluded: an object inside a
    walled pocket that only the few cameras facing its opening see; sparse-objects: small objects spread out."""
    num_cameras: int = 48
    """Number of cameras (images), split evenly over the rings."""
    width: int = 96
    """Image width in pixels."""
    height: int = 72
    """Image height in pixels."""
    num_rings: int = 3
    """Camera rings at different heights (all cameras look at the scene centre)."""
    seed: int = 0
    """Seeds object placement jitter, colours, textures, camera jitter and the 3D point samples."""
    num_points: int = 4000
    """3D points in points3D.bin (surface samples seen by at least 2 cameras)."""
    fov_deg: float = 60.0
    """Horizontal field of view in degrees (PINHOLE, square pixels, principal point at the image centre)."""
    supersample: int = 2
    """Rays per pixel along each axis (2 = 2x2 supersampling, 1 = one ray through each pixel centre)."""
    object_point_fraction: float = 0.5
    """Share of the 3D points on objects and occluders; the rest lie on the ground and backdrop."""

    def validate(self) -> None:
        """Raise SceneSpecError (one line) for a bad field."""
        if self.layout not in LAYOUTS:
            raise SceneSpecError(f"unknown layout {self.layout!r}; choose one of: {', '.join(LAYOUTS)}")
        if self.num_rings < 1:
            raise SceneSpecError(f"--num-rings must be >= 1 (got {self.num_rings})")
        if self.num_cameras < max(2, self.num_rings):
            raise SceneSpecError(
                f"--num-cameras must be >= 2 and >= --num-rings ({self.num_rings}) (got {self.num_cameras})"
            )
        if self.width < 8 or self.height < 8:
            raise SceneSpecError(f"image size must be at least 8x8 pixels (got {self.width}x{self.height})")
        if self.width * self.height > 4096 * 4096:
            raise SceneSpecError(f"image size {self.width}x{self.height} is too large (max 4096x4096 pixels)")
        if self.num_points < 0:
            raise SceneSpecError(f"--num-points must be >= 0 (got {self.num_points})")
        if not 10.0 <= self.fov_deg <= 150.0:
            raise SceneSpecError(f"--fov-deg must be within [10, 150] (got {self.fov_deg})")
        if not 1 <= self.supersample <= 8:
            raise SceneSpecError(f"--supersample must be within [1, 8] (got {self.supersample})")
        if not 0.0 <= self.object_point_fraction <= 1.0:
            raise SceneSpecError(f"--object-point-fraction must be within [0, 1] (got {self.object_point_fraction})")

    @property
    def focal(self) -> float:
        """fx = fy in pixels."""
        return 0.5 * self.width / math.tan(math.radians(self.fov_deg) / 2)


# ----------------------------------------------------------------------------------------------------------
# Textures


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice points (same shape as ix)."""
    m = 0xFFFFFFFF
    h = (ix.astype(np.int64) * 0x8DA6B343) ^ (iy.astype(np.int64) * 0xD8163841) ^ ((seed * 0xCB1AB31F) & m)
    h &= m
    h ^= h >> 15
    h = (h * 0x2C1B3C6D) & m
    h ^= h >> 12
    h = (h * 0x297A2D39) & m
    h ^= h >> 15
    return h.astype(np.float64) / 2.0**32


def value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] on a unit lattice; u, v: (M,) -> (M,)."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    a, b = _hash01(iu, iv, seed), _hash01(iu + 1, iv, seed)
    c, d = _hash01(iu, iv + 1, seed), _hash01(iu + 1, iv + 1, seed)
    return (a * (1 - su) + b * su) * (1 - sv) + (c * (1 - su) + d * su) * sv


@dataclass
class Texture:
    """A two-colour procedural pattern on a surface's (u, v) coordinates in metres, times fine noise."""

    kind: Literal["checker", "stripes", "rings", "noise", "solid"]
    color_a: Tuple[float, float, float]
    color_b: Tuple[float, float, float]
    cell: float = 0.2
    """Pattern period (metres)."""
    grain: float = 0.15
    """Amplitude of the fine multiplicative noise (gives every surface texture to fit)."""
    grain_cell: float = 0.15
    """Period of the fine noise (metres): kept near a few pixels at the default resolution, not below a pixel,
    so the images do not alias."""
    seed: int = 0

    def albedo(self, uv: np.ndarray) -> np.ndarray:
        """uv: (M, 2) metres -> albedo (M, 3) in [0, 1]."""
        u, v = uv[:, 0] / self.cell, uv[:, 1] / self.cell
        if self.kind == "checker":
            w = ((np.floor(u) + np.floor(v)) % 2).astype(np.float64)
        elif self.kind == "stripes":  # diagonal stripes
            w = (np.floor(u + v) % 2).astype(np.float64)
        elif self.kind == "rings":  # horizontal bands (v is height on walls and cylinders)
            w = (np.floor(v) % 2).astype(np.float64)
        elif self.kind == "noise":
            w = np.clip(1.6 * (value_noise(u, v, self.seed) - 0.5) + 0.5, 0, 1)
        else:
            w = np.zeros_like(u)
        a, b = np.asarray(self.color_a), np.asarray(self.color_b)
        base = a[None] * (1 - w[:, None]) + b[None] * w[:, None]
        fine = value_noise(uv[:, 0] / self.grain_cell, uv[:, 1] / self.grain_cell, self.seed + 7919) - 0.5
        return np.clip(base * (1 + self.grain * 2 * fine[:, None]), 0, 1)


# ----------------------------------------------------------------------------------------------------------
# Primitives (scene frame, z up). intersect: o, d (N, 3), d unit -> t (N,) with inf for a miss.
# surface: hit points (M, 3) -> unit normals (M, 3), texture coordinates (M, 2) in metres.


@dataclass
class Primitive:
    name: str
    texture: Texture
    role: Literal["object", "occluder", "ground", "backdrop"] = "object"

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def surface(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def bound(self) -> Optional[Tuple[np.ndarray, float]]:
        """Bounding sphere (centre (3,), radius), used to skip rays that cannot hit; None: unbounded."""
        return None

    def describe(self) -> dict:
        out = {"name": self.name, "kind": type(self).__name__.lower(), "role": self.role}
        for key, value in asdict(self).items():
            if key not in ("name", "texture", "role"):
                out[key] = _scene_vec(value) if key == "center" else value
        out["texture"] = self.texture.kind
        out["color"] = [round(c, 3) for c in self.texture.color_a]
        return out


def _scene_vec(v) -> list:
    """A scene-frame point -> its COLMAP-world coordinates (list, for JSON)."""
    return [round(float(x), 6) for x in SCENE_TO_COLMAP @ np.asarray(v, dtype=np.float64)]


@dataclass
class Sphere(Primitive):
    center: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.5

    def intersect(self, o, d):
        oc = o - np.asarray(self.center)
        b = np.einsum("ij,ij->i", oc, d)
        c = np.einsum("ij,ij->i", oc, oc) - self.radius**2
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            s = np.sqrt(disc)
        t0, t1 = -b - s, -b + s
        t = np.where(t0 > _EPS, t0, t1)  # t1 only matters for rays starting inside (never for cameras)
        return np.where((disc >= 0) & (t > _EPS), t, np.inf)

    def bound(self):
        return np.asarray(self.center, dtype=np.float64), self.radius

    def surface(self, p):
        q = p - np.asarray(self.center)
        n = q / np.linalg.norm(q, axis=1, keepdims=True)
        uv = np.stack([np.arctan2(q[:, 1], q[:, 0]) * self.radius, np.arccos(np.clip(n[:, 2], -1, 1)) * self.radius], 1)
        return n, uv


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Box(Primitive):
    center: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    half: Tuple[float, float, float] = (0.5, 0.5, 0.5)
    yaw_deg: float = 0.0

    def _local(self, x: np.ndarray, point: bool) -> np.ndarray:
        r = _rot_z(math.radians(self.yaw_deg))
        return ((x - np.asarray(self.center)) if point else x) @ r  # row-vector form of R^T x

    def intersect(self, o, d):
        lo, ld = self._local(o, True), self._local(d, False)
        h = np.asarray(self.half)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / np.where(ld == 0, 1e-300, ld)
            t1, t2 = (-h - lo) * inv, (h - lo) * inv
        lo_t, hi_t = np.minimum(t1, t2), np.maximum(t1, t2)
        tmin = np.maximum(np.maximum(lo_t[:, 0], lo_t[:, 1]), lo_t[:, 2])  # faster than .max(1) on (N, 3)
        tmax = np.minimum(np.minimum(hi_t[:, 0], hi_t[:, 1]), hi_t[:, 2])
        t = np.where(tmin > _EPS, tmin, tmax)
        return np.where((tmax >= tmin) & (t > _EPS), t, np.inf)

    def bound(self):
        return np.asarray(self.center, dtype=np.float64), float(np.linalg.norm(self.half))

    def surface(self, p):
        lp = self._local(p, True)
        h = np.asarray(self.half)
        axis = np.argmax(np.abs(lp) / h, axis=1)
        nl = np.zeros_like(lp)
        nl[np.arange(len(lp)), axis] = np.sign(lp[np.arange(len(lp)), axis])
        n = nl @ _rot_z(math.radians(self.yaw_deg)).T
        shifted = lp + h  # texture coordinates from the box corner, in metres
        uv = np.where(
            (axis == 0)[:, None], shifted[:, [1, 2]], np.where((axis == 1)[:, None], shifted[:, [0, 2]], shifted[:, [0, 1]])
        )
        return n, uv


@dataclass
class Cylinder(Primitive):
    """Vertical capped cylinder from z0 to z1."""

    center: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.3
    z0: float = 0.0
    z1: float = 1.0

    def intersect(self, o, d):
        cx, cy = self.center[0], self.center[1]
        ox, oy = o[:, 0] - cx, o[:, 1] - cy
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = ox * d[:, 0] + oy * d[:, 1]
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = (-b - np.sqrt(disc)) / a
            zs = o[:, 2] + ts * d[:, 2]
            side = np.where((a > 1e-12) & (disc >= 0) & (ts > _EPS) & (zs >= self.z0) & (zs <= self.z1), ts, np.inf)
            best = side
            for zc in (self.z0, self.z1):
                tc = (zc - o[:, 2]) / d[:, 2]
                xc, yc = ox + tc * d[:, 0], oy + tc * d[:, 1]
                cap = np.where((tc > _EPS) & (xc * xc + yc * yc <= self.radius**2), tc, np.inf)
                best = np.minimum(best, cap)
        return best

    def bound(self):
        half_h = (self.z1 - self.z0) / 2
        return np.array([self.center[0], self.center[1], self.z0 + half_h]), math.hypot(self.radius, half_h)

    def surface(self, p):
        q = p - np.array([self.center[0], self.center[1], 0.0])
        rho = np.hypot(q[:, 0], q[:, 1])
        d_side, d_top, d_bot = np.abs(rho - self.radius), np.abs(q[:, 2] - self.z1), np.abs(q[:, 2] - self.z0)
        which = np.argmin(np.stack([d_side, d_top, d_bot], 1), axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            n_side = np.stack([q[:, 0] / rho, q[:, 1] / rho, np.zeros_like(rho)], 1)
        n = np.where((which == 0)[:, None], n_side, np.where((which == 1)[:, None], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]))
        uv_side = np.stack([np.arctan2(q[:, 1], q[:, 0]) * self.radius, q[:, 2]], 1)
        uv = np.where((which == 0)[:, None], uv_side, q[:, :2])
        return n, uv


@dataclass
class Disc(Primitive):
    """Horizontal disc at z = 0 (the ground), seen from above."""

    radius: float = 8.0

    def intersect(self, o, d):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[:, 2] / d[:, 2]
            x, y = o[:, 0] + t * d[:, 0], o[:, 1] + t * d[:, 1]
        return np.where((d[:, 2] < 0) & (t > _EPS) & (x * x + y * y <= self.radius**2), t, np.inf)

    def surface(self, p):
        return np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape).copy(), p[:, :2].copy()


@dataclass
class Backdrop(Primitive):
    """Inside of a vertical cylinder around everything (z from 0 to `top`), seen from within."""

    radius: float = 8.0
    top: float = 6.0

    def intersect(self, o, d):
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - self.radius**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (-b + np.sqrt(disc)) / a  # far root: the rays start inside
            z = o[:, 2] + t * d[:, 2]
        return np.where((a > 1e-12) & (disc >= 0) & (t > _EPS) & (z >= 0) & (z <= self.top), t, np.inf)

    def surface(self, p):
        rho = np.hypot(p[:, 0], p[:, 1])
        n = np.stack([-p[:, 0] / rho, -p[:, 1] / rho, np.zeros_like(rho)], 1)
        uv = np.stack([np.arctan2(p[:, 1], p[:, 0]) * self.radius, p[:, 2]], 1)
        return n, uv


# ----------------------------------------------------------------------------------------------------------
# Scene


@dataclass
class Scene:
    """Primitives plus lighting; casts and shades rays in the scene frame (z up)."""

    prims: List[Primitive]
    target: np.ndarray
    """(3,) point every camera looks at (scene frame)."""
    hidden: List[str] = field(default_factory=list)
    """Objects the layout places so that only some cameras see them."""
    light: np.ndarray = field(default_factory=lambda: _unit(np.array([0.45, -0.35, 0.82])))
    """(3,) unit direction towards the light."""
    ambient: float = 0.42
    sky_low: Tuple[float, float, float] = (0.80, 0.86, 0.93)
    sky_high: Tuple[float, float, float] = (0.42, 0.58, 0.85)

    def cast(self, o: np.ndarray, d: np.ndarray, only: Optional[Sequence[int]] = None) -> Tuple[np.ndarray, np.ndarray]:
        """o, d: (N, 3), d unit -> nearest hit distance t (N,) (inf: none) and primitive index (N,) (-1: none)."""
        ids = list(range(len(self.prims)) if only is None else only)
        t = np.full(len(o), np.inf)
        idx = np.full(len(o), -1, dtype=np.int64)
        bounds = {i: self.prims[i].bound() for i in ids}
        bounded = [i for i in ids if bounds[i] is not None]
        group = np.arange(len(o))
        if len(bounded) > 1:  # cull against a sphere around all bounded primitives first, then each one's
            centre = np.mean([bounds[i][0] for i in bounded], axis=0)
            radius = max(np.linalg.norm(bounds[i][0] - centre) + bounds[i][1] for i in bounded)
            group = _through_sphere(o, d, centre, radius)
        for i in ids:
            if bounds[i] is None:
                rows = slice(None)
            else:
                rows = group[_through_sphere(o[group], d[group], *bounds[i])]
                if len(rows) == 0:
                    continue
            ti = self.prims[i].intersect(o[rows], d[rows])
            sub_t = t[rows]
            closer = ti < sub_t
            sub_t[closer] = ti[closer]
            t[rows] = sub_t
            sub_idx = idx[rows]
            sub_idx[closer] = i
            idx[rows] = sub_idx
        return t, idx

    def shade(self, p: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Hit points p (M, 3) on primitives idx (M,) (all >= 0) -> linear RGB (M, 3) in [0, 1]."""
        rgb = np.zeros_like(p)
        normals = np.zeros_like(p)
        for i in np.unique(idx):
            m = idx == i
            n, uv = self.prims[i].surface(p[m])
            rgb[m] = self.prims[i].texture.albedo(uv)
            normals[m] = n
        lambert = np.clip(normals @ self.light, 0, None)
        lit = lambert > 0
        casters = [i for i, prim in enumerate(self.prims) if prim.role in ("object", "occluder")]
        if lit.any() and casters:
            origin = p[lit] + 1e-5 * normals[lit]
            t_shadow, _ = self.cast(origin, np.broadcast_to(self.light, origin.shape), casters)
            lambert[np.flatnonzero(lit)[np.isfinite(t_shadow)]] = 0.0
        return np.clip(rgb * (self.ambient + (1 - self.ambient) * lambert)[:, None], 0, 1)

    def render_rays(self, o: np.ndarray, d: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays (N, 3) -> RGB (N, 3), primitive index (N,) (-1: sky), distance t (N,)."""
        rgb = np.empty((len(o), 3))
        t_all = np.empty(len(o))
        idx_all = np.empty(len(o), dtype=np.int64)
        for s in range(0, len(o), _CHUNK):
            oc, dc = o[s : s + _CHUNK], d[s : s + _CHUNK]
            t, idx = self.cast(oc, dc)
            hit = idx >= 0
            up = np.clip(dc[:, 2], 0, 1)[:, None]
            out = np.asarray(self.sky_low) * (1 - up) + np.asarray(self.sky_high) * up
            if hit.any():
                out[hit] = self.shade(oc[hit] + t[hit, None] * dc[hit], idx[hit])
            rgb[s : s + _CHUNK], t_all[s : s + _CHUNK], idx_all[s : s + _CHUNK] = out, t, idx
        return rgb, idx_all, t_all


def _through_sphere(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the rays (N, 3) that pass through a sphere ahead of (or around) their origin."""
    oc = o - centre
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - radius**2
    return np.flatnonzero((b * b >= c) & ((b < 0) | (c < 0)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _hsv(h: float, s: float, v: float) -> Tuple[float, float, float]:
    """HSV (h in degrees) -> RGB tuple in [0, 1]."""
    h = (h % 360) / 60
    c = v * s
    x = c * (1 - abs(h % 2 - 1))
    r, g, b = [(c, x, 0), (x, c, 0), (0, c, x), (0, x, c), (x, 0, c), (c, 0, x)][int(h) % 6]
    return (r + v - c, g + v - c, b + v - c)


def _tex(rng: np.random.Generator, kind: str, hue: float, cell: float, sat: float = 0.75) -> Texture:
    """A texture in a hue (jittered by the seed), the second colour a lighter, less saturated tint."""
    h = hue + rng.uniform(-8, 8)
    return Texture(
        kind=kind,  # type: ignore[arg-type]
        color_a=_hsv(h, sat, 0.85),
        color_b=_hsv(h + 25, sat * 0.35, 0.97),
        cell=cell * rng.uniform(0.9, 1.1),
        seed=int(rng.integers(0, 2**31)),
    )


def _surroundings(rng: np.random.Generator) -> List[Primitive]:
    """Ground disc and backdrop shared by all layouts: large, textured, fill every view."""
    ground = Disc(
        "ground",
        Texture("checker", (0.55, 0.52, 0.47), (0.80, 0.78, 0.72), cell=0.5, grain=0.25, grain_cell=0.3, seed=int(rng.integers(2**31))),
        role="ground",
        radius=9.0,
    )
    backdrop = Backdrop(
        "backdrop",
        Texture("noise", (0.35, 0.45, 0.38), (0.85, 0.80, 0.62), cell=0.9, grain=0.2, grain_cell=0.6, seed=int(rng.integers(2**31))),
        role="backdrop",
        radius=9.0,
        top=7.0,
    )
    return [ground, backdrop]


def build_scene(layout: str = "ring", seed: int = 0) -> Scene:
    """The primitives of one layout; positions, colours and textures jittered deterministically by `seed`."""
    if layout not in LAYOUTS:
        raise SceneSpecError(f"unknown layout {layout!r}; choose one of: {', '.join(LAYOUTS)}")
    rng = np.random.default_rng([seed, LAYOUTS.index(layout)])

    def jit(x: float, y: float, amount: float = 0.08) -> Tuple[float, float]:
        return x + rng.uniform(-amount, amount), y + rng.uniform(-amount, amount)

    prims: List[Primitive] = _surroundings(rng)
    hidden: List[str] = []
    target = np.array([0.0, 0.0, 0.45])
    if layout == "ring":
        x, y = jit(0.75, 0.45)
        prims.append(Sphere("red_sphere", _tex(rng, "stripes", 0, 0.3), center=(x, y, 0.45), radius=0.45))
        x, y = jit(-0.55, 0.75)
        prims.append(Box("green_box", _tex(rng, "checker", 120, 0.23), center=(x, y, 0.35), half=(0.35, 0.35, 0.35),
                         yaw_deg=float(rng.uniform(10, 35))))
        x, y = jit(-0.1, -0.85)
        prims.append(Cylinder("blue_cylinder", _tex(rng, "rings", 220, 0.18), center=(x, y, 0.0), radius=0.3, z0=0.0, z1=1.1))
        x, y = jit(0.95, -0.65)
        prims.append(Sphere("yellow_sphere", _tex(rng, "noise", 52, 0.2), center=(x, y, 0.28), radius=0.28))
        # A wall on the -x side hides the magenta sphere behind it from the cameras on the +x side.
        prims.append(Box("wall", _tex(rng, "rings", 30, 0.2, sat=0.35), role="occluder", center=(-1.35, 0.0, 0.6),
                         half=(0.08, 0.85, 0.6), yaw_deg=float(rng.uniform(-6, 6))))
        x, y = jit(-1.85, -0.05, 0.05)
        prims.append(Sphere("magenta_sphere", _tex(rng, "checker", 300, 0.16), center=(x, y, 0.3), radius=0.3))
        hidden.append("magenta_sphere")
    elif layout == "occluded":
        x, y = jit(-0.55, 0.55)
        prims.append(Sphere("red_sphere", _tex(rng, "stripes", 0, 0.3), center=(x, y, 0.42), radius=0.42))
        x, y = jit(-0.75, -0.5)
        prims.append(Box("green_box", _tex(rng, "checker", 120, 0.23), center=(x, y, 0.3), half=(0.3, 0.3, 0.3),
                         yaw_deg=float(rng.uniform(10, 35))))
        x, y = jit(0.1, 0.0)
        prims.append(Cylinder("blue_cylinder", _tex(rng, "rings", 220, 0.18), center=(x, y, 0.0), radius=0.25, z0=0.0, z1=0.9))
        # A pocket on the +x side, open only towards +x: its gold sphere is seen only by the cameras facing
        # the opening. Walls are taller than the line of sight from the highest ring over them.
        wall_tex = _tex(rng, "rings", 30, 0.2, sat=0.35)
        prims.append(Box("pocket_back", wall_tex, role="occluder", center=(1.0, 0.0, 0.8), half=(0.07, 0.62, 0.8)))
        prims.append(Box("pocket_left", wall_tex, role="occluder", center=(1.45, 0.55, 0.8), half=(0.45, 0.07, 0.8)))
        prims.append(Box("pocket_right", wall_tex, role="occluder", center=(1.45, -0.55, 0.8), half=(0.45, 0.07, 0.8)))
        prims.append(Sphere("gold_sphere", _tex(rng, "checker", 45, 0.16), center=(1.42, rng.uniform(-0.05, 0.05), 0.3), radius=0.3))
        hidden.append("gold_sphere")
    else:  # sparse-objects: a handful of small objects scattered over a wide area, no occluders
        kinds = ["sphere", "box", "cylinder", "sphere", "box", "cylinder"]
        names = ["red", "green", "blue", "yellow", "cyan", "magenta"]
        hues = [0, 120, 220, 52, 185, 300]
        textures = ["stripes", "checker", "rings", "noise", "checker", "stripes"]
        placed: List[Tuple[float, float]] = []
        for name, kind, hue, texture in zip(names, kinds, hues, textures):
            for _ in range(200):  # rejection sampling: keep the objects apart
                r, a = 2.1 * math.sqrt(rng.uniform(0.05, 1.0)), rng.uniform(0, 2 * math.pi)
                x, y = r * math.cos(a), r * math.sin(a)
                if all(math.hypot(x - px, y - py) > 0.75 for px, py in placed):
                    break
            placed.append((x, y))
            size = rng.uniform(0.16, 0.26)
            tex = _tex(rng, texture, hue, 0.12)
            if kind == "sphere":
                prims.append(Sphere(f"{name}_sphere", tex, center=(x, y, size), radius=size))
            elif kind == "box":
                prims.append(Box(f"{name}_box", tex, center=(x, y, size), half=(size, size, size), yaw_deg=float(rng.uniform(0, 90))))
            else:
                prims.append(Cylinder(f"{name}_cylinder", tex, center=(x, y, 0.0), radius=0.7 * size, z0=0.0, z1=3 * size))
        target = np.array([0.0, 0.0, 0.2])
    return Scene(prims=prims, target=target, hidden=hidden)


# ----------------------------------------------------------------------------------------------------------
# Cameras


@dataclass
class RigCamera:
    """One camera: COLMAP world-to-camera pose and where it sits on the rig (scene frame)."""

    name: str
    image_id: int
    ring: int
    azimuth_deg: float
    center: np.ndarray
    """(3,) camera centre, scene frame."""
    c2w: np.ndarray
    """(3, 3) camera-to-world rotation, scene frame; columns = camera x (right), y (down), z (forward)."""

    def rays(self, spec: SceneSpec, ss: Optional[int] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Ray origins and unit directions (H * W * ss * ss, 3), ordered row, column, sub-row, sub-column."""
        ss = spec.supersample if ss is None else ss
        sub = (np.arange(ss) + 0.5) / ss
        v = (np.arange(spec.height)[:, None] + sub[None, :]).reshape(-1)  # (H*ss,)
        u = (np.arange(spec.width)[:, None] + sub[None, :]).reshape(-1)  # (W*ss,)
        vv, uu = np.meshgrid(v, u, indexing="ij")  # (H*ss, W*ss)
        # reorder so each pixel's ss*ss samples are contiguous: (H, ss, W, ss) -> (H, W, ss, ss)
        vv = vv.reshape(spec.height, ss, spec.width, ss).transpose(0, 2, 1, 3).reshape(-1)
        uu = uu.reshape(spec.height, ss, spec.width, ss).transpose(0, 2, 1, 3).reshape(-1)
        f, cx, cy = spec.focal, spec.width / 2, spec.height / 2
        dirs = np.stack([(uu - cx) / f, (vv - cy) / f, np.ones_like(uu)], 1) @ self.c2w.T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        return np.broadcast_to(self.center, dirs.shape), dirs

    def project(self, p: np.ndarray, spec: SceneSpec) -> Tuple[np.ndarray, np.ndarray]:
        """Scene points (M, 3) -> pixel coordinates (M, 2) (COLMAP: pixel (0, 0) spans [0, 1)^2), depth (M,)."""
        pc = (p - self.center) @ self.c2w  # world -> camera: R^T (p - C)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = spec.focal * pc[:, :2] / z[:, None] + np.array([spec.width / 2, spec.height / 2])
        return uv, z

    def colmap_pose(self) -> Tuple[np.ndarray, np.ndarray]:
        """World-to-camera rotation (3, 3) and translation (3,) in the COLMAP world frame."""
        r_w2c = self.c2w.T @ SCENE_TO_COLMAP.T  # p_cam = R^T (S^T p_colmap - C)
        return r_w2c, -r_w2c @ (SCENE_TO_COLMAP @ self.center)


def camera_rig(spec: SceneSpec, scene: Scene) -> List[RigCamera]:
    """Cameras on `num_rings` rings (low to high), all looking at the scene target; capture order = ring-major."""
    rng = np.random.default_rng([spec.seed, 1000 + LAYOUTS.index(spec.layout)])
    heights = np.linspace(0.35, 2.3, spec.num_rings) if spec.num_rings > 1 else np.array([1.1])
    counts = [spec.num_cameras // spec.num_rings + (k < spec.num_cameras % spec.num_rings) for k in range(spec.num_rings)]
    distance = 4.2  # same distance to the target from every ring
    up = np.array([0.0, 0.0, 1.0])
    cams: List[RigCamera] = []
    for ring, (h, n) in enumerate(zip(heights, counts)):
        radius = math.sqrt(max(distance**2 - (h - scene.target[2]) ** 2, 1.0))
        for j in range(n):
            # rings staggered by half a step so the union covers more azimuths; small seeded jitter
            az = 2 * math.pi * (j + 0.5 * (ring % 2) + rng.uniform(-0.15, 0.15)) / n
            rr = radius * rng.uniform(0.97, 1.03)
            hh = h + rng.uniform(-0.05, 0.05)
            center = np.array([rr * math.cos(az), rr * math.sin(az), hh])
            fwd = _unit(scene.target - center)
            right = _unit(np.cross(fwd, up))
            down = np.cross(fwd, right)
            idx = len(cams)
            cams.append(RigCamera(f"{idx:04d}.png", idx + 1, ring, math.degrees(az) % 360, center, np.stack([right, down, fwd], 1)))
    return cams


# ----------------------------------------------------------------------------------------------------------
# Rendering, points, tracks


def render_camera(scene: Scene, cam: RigCamera, spec: SceneSpec) -> Tuple[np.ndarray, np.ndarray]:
    """-> image (H, W, 3) uint8, primitive index per sample (H, W, ss*ss) (-1: sky)."""
    o, d = cam.rays(spec)
    rgb, idx, _ = scene.render_rays(o, d)
    ss2 = spec.supersample**2
    img = rgb.reshape(spec.height, spec.width, ss2, 3).mean(2)
    return _to_u8(img), idx.reshape(spec.height, spec.width, ss2)


def _to_u8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def visibility(scene: Scene, cams: List[RigCamera], points: np.ndarray, spec: SceneSpec) -> Tuple[np.ndarray, np.ndarray]:
    """Which cameras see which points: in the image and not occluded (the ray from the camera centre hits
    nothing closer than the point).

    points: (P, 3) scene frame, on surfaces -> visible (C, P) bool, pixel coordinates (C, P, 2)."""
    vis = np.zeros((len(cams), len(points)), dtype=bool)
    uv_all = np.zeros((len(cams), len(points), 2))
    for c, cam in enumerate(cams):
        uv, z = cam.project(points, spec)
        inside = (z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < spec.width) & (uv[:, 1] >= 0) & (uv[:, 1] < spec.height)
        cand = np.flatnonzero(inside)
        if len(cand):
            delta = points[cand] - cam.center
            dist = np.linalg.norm(delta, axis=1)
            t, _ = scene.cast(np.broadcast_to(cam.center, delta.shape), delta / dist[:, None])
            # the point itself is the first hit (up to round-off) unless something is in front of it
            vis[c, cand] = t >= dist * (1 - 1e-7) - 1e-7
        uv_all[c] = uv
    return vis, uv_all


def sample_points(
    scene: Scene, cams: List[RigCamera], spec: SceneSpec, rng: np.random.Generator
) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Up to `num_points` surface points seen by >= 2 cameras, in random order. Candidates are the hits of random
    rays through random pixels of random cameras (density follows image coverage, like SfM); a share
    `object_point_fraction` goes to objects and occluders (SfM finds most points on the textured subject, not on
    the far ground), the rest to the ground and backdrop; a candidate is kept when its track has >= 2 views.

    -> points (P, 3) scene frame, colours (P, 3) uint8, primitive index (P,), visible (C, P), pixels (C, P, 2)."""
    on_object = np.array([prim.role in ("object", "occluder") for prim in scene.prims])
    want = {True: int(round(spec.num_points * spec.object_point_fraction)), False: 0}
    want[False] = spec.num_points - want[True]
    pools: Dict[bool, List[Tuple[np.ndarray, np.ndarray]]] = {True: [], False: []}
    have = {True: 0, False: 0}
    f, cx, cy = spec.focal, spec.width / 2, spec.height / 2
    for _ in range(30):  # a few rounds: objects cover a small part of the images
        if spec.num_points == 0 or (have[True] >= want[True] and have[True] + have[False] >= spec.num_points):
            break
        n = max(4 * spec.num_points, 256)
        cam_ids = rng.integers(0, len(cams), n)
        px = rng.uniform([0, 0], [spec.width, spec.height], (n, 2))
        o = np.stack([cams[c].center for c in cam_ids])
        local = np.stack([(px[:, 0] - cx) / f, (px[:, 1] - cy) / f, np.ones(n)], 1)
        d = np.einsum("nij,nj->ni", np.stack([cams[c].c2w for c in cam_ids]), local)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, idx = scene.cast(o, d)
        for obj in (True, False):
            rows = np.flatnonzero((idx >= 0) & (on_object[np.maximum(idx, 0)] == obj))
            rows = rows[: int(1.5 * max(want[obj] - have[obj], 0)) + 16]  # tracks are the costly part
            p = o[rows] + t[rows, None] * d[rows]
            keep = visibility(scene, cams, p, spec)[0].sum(0) >= 2
            pools[obj].append((p[keep], idx[rows][keep]))
            have[obj] += int(keep.sum())
    cat = {
        obj: (
            np.concatenate([a for a, _ in pools[obj]] or [np.zeros((0, 3))]),
            np.concatenate([b for _, b in pools[obj]] or [np.zeros(0, np.int64)]),
        )
        for obj in (True, False)
    }
    n_obj = min(len(cat[True][0]), want[True])
    n_sur = min(len(cat[False][0]), spec.num_points - n_obj)
    n_obj = min(len(cat[True][0]), spec.num_points - n_sur)  # top up with object points if the rest ran short
    points = np.concatenate([cat[True][0][:n_obj], cat[False][0][:n_sur]])
    prim = np.concatenate([cat[True][1][:n_obj], cat[False][1][:n_sur]])
    order = rng.permutation(len(points))
    points, prim = points[order], prim[order]
    colors = _to_u8(scene.shade(points, prim)) if len(points) else np.zeros((0, 3), dtype=np.uint8)
    vis, uv = visibility(scene, cams, points, spec)
    return points, colors, prim, vis, uv


# ----------------------------------------------------------------------------------------------------------
# Writing


def _write_colmap(
    model_dir: Path, spec: SceneSpec, cams: List[RigCamera], points: np.ndarray, colors: np.ndarray, vis: np.ndarray, uv: np.ndarray
) -> None:
    """cameras/images/points3D.bin via pycolmap; image ids 1..N in capture (= file-name) order; each image's
    keypoints are the exact projections of the points it sees, in point order."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    f = spec.focal
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=spec.width, height=spec.height, params=[f, f, spec.width / 2, spec.height / 2], camera_id=1)
    )
    kp_index = np.full(vis.shape, -1, dtype=np.int64)  # (C, P) keypoint index of point p in image c
    for c, cam in enumerate(cams):
        seen = np.flatnonzero(vis[c])
        kp_index[c, seen] = np.arange(len(seen))
        image = pycolmap.Image(name=cam.name, keypoints=uv[c, seen].astype(np.float64).reshape(-1, 2), camera_id=1, image_id=cam.image_id)
        r, t = cam.colmap_pose()
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(r), t))
    world = points @ SCENE_TO_COLMAP.T
    for p in range(len(points)):
        track = pycolmap.Track([pycolmap.TrackElement(cams[c].image_id, int(kp_index[c, p])) for c in np.flatnonzero(vis[:, p])])
        rec.add_point3D(world[p], track, colors[p])
    rec.update_point_3d_errors()
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write(str(model_dir))


def _ground_truth(
    spec: SceneSpec, scene: Scene, cams: List[RigCamera], coverage: np.ndarray, min_pixels: float, points_per_prim: np.ndarray
) -> dict:
    """ground_truth.json contents. coverage: (C, num_prims) fraction of each image covered by each primitive;
    points_per_prim: (num_prims,) 3D points sampled on each primitive."""
    threshold = min_pixels / (spec.width * spec.height)
    sees = coverage >= threshold
    names = [p.name for p in scene.prims]
    objects = []
    for i, prim in enumerate(scene.prims):
        entry = prim.describe()
        entry["seen_by"] = [cams[c].name for c in np.flatnonzero(sees[:, i])]
        entry["num_points3D"] = int(points_per_prim[i])
        objects.append(entry)
    limited = sorted(
        (
            {"name": o["name"], "num_seen_by": len(o["seen_by"]), "fraction_of_cameras": round(len(o["seen_by"]) / len(cams), 4),
             "seen_by": o["seen_by"]}
            for o in objects
            if o["role"] in ("object", "occluder") and len(o["seen_by"]) < 0.5 * len(cams)
        ),
        key=lambda e: e["num_seen_by"],
    )
    f = spec.focal
    return {
        "generator": "hpgs_ns.scenes.synthetic",
        "layout": spec.layout,
        "seed": spec.seed,
        "spec": asdict(spec),
        "frame": "COLMAP world of sparse/0 (gravity along +y; cameras x right, y down, z forward); metres",
        "up": _scene_vec([0, 0, 1]),
        "target": _scene_vec(scene.target),
        "light_direction": _scene_vec(scene.light),
        "intrinsics": {"model": "PINHOLE", "width": spec.width, "height": spec.height, "fx": f, "fy": f,
                       "cx": spec.width / 2, "cy": spec.height / 2},
        "sees_min_pixels": min_pixels,
        "num_points3D": int(points_per_prim.sum()),
        "cameras": [
            {
                "name": cam.name,
                "image_id": cam.image_id,
                "ring": cam.ring,
                "height": round(float(cam.center[2]), 6),
                "azimuth_deg": round(cam.azimuth_deg, 4),
                "center": _scene_vec(cam.center),
                "look": _scene_vec(cam.c2w[:, 2]),
                "sees": [names[i] for i in np.flatnonzero(sees[c])],
                "coverage": {names[i]: round(float(coverage[c, i]), 5) for i in np.flatnonzero(coverage[c] > 0)},
            }
            for c, cam in enumerate(cams)
        ],
        "objects_note": "center in the COLMAP world frame; radius/half sizes in metres along the scene axes "
        "(x, y, up); yaw_deg about the up axis; cylinders span heights z0..z1 above the ground",
        "objects": objects,
        "hidden": [
            {"name": n, "seen_by": objects[names.index(n)]["seen_by"], "num_points3D": objects[names.index(n)]["num_points3D"]}
            for n in scene.hidden
        ],
        "limited_visibility": limited,
    }


def _prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise SceneSpecError(f"output path {out_dir} exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise SceneSpecError(f"output folder {out_dir} exists and is not empty; pass --overwrite to replace it")
    if not out_dir.parent.exists():
        out_dir.parent.mkdir(parents=True, exist_ok=True)


def generate(spec: SceneSpec, out_dir: Path, overwrite: bool = False, min_pixels: float = 2.0) -> Path:
    """Write the scene described by `spec` to `out_dir` (built in a temp folder beside it, then renamed into
    place, so an interrupted run leaves no half-written scene). Returns the resolved output folder."""
    from PIL import Image

    spec.validate()
    out_dir = Path(out_dir).expanduser().resolve()
    _prepare_out_dir(out_dir, overwrite)
    scene = build_scene(spec.layout, spec.seed)
    cams = camera_rig(spec, scene)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        (tmp / "images").mkdir()
        coverage = np.zeros((len(cams), len(scene.prims)))
        for c, cam in enumerate(cams):
            img, idx = render_camera(scene, cam, spec)
            Image.fromarray(img).save(tmp / "images" / cam.name)
            counts = np.bincount(idx[idx >= 0].reshape(-1), minlength=len(scene.prims))
            coverage[c] = counts / idx.size
        rng = np.random.default_rng([spec.seed, 2000 + LAYOUTS.index(spec.layout)])
        points, colors, prim, vis, uv = sample_points(scene, cams, spec, rng)
        _write_colmap(tmp / "sparse" / "0", spec, cams, points, colors, vis, uv)
        truth = _ground_truth(spec, scene, cams, coverage, min_pixels, np.bincount(prim, minlength=len(scene.prims)))
        (tmp / "ground_truth.json").write_text(json.dumps(truth, indent=1) + "\n")
        os.chmod(tmp, 0o755)  # mkdtemp makes it 0700
        if out_dir.exists():  # --overwrite (or an empty folder): swap, then remove the old one
            old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
            os.rename(out_dir, old / "scene")
            os.rename(tmp, out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            try:
                os.rename(tmp, out_dir)
            except OSError as err:  # another run wrote the same folder meanwhile
                raise SceneSpecError(f"output folder {out_dir} appeared while generating; pass --overwrite to replace it") from err
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def make_scene(
    out_dir: Path | str,
    layout: str = "ring",
    num_cameras: int = 48,
    width: int = 96,
    height: int = 72,
    num_rings: int = 3,
    num_points: int = 4000,
    seed: int = 0,
    fov_deg: float = 60.0,
    supersample: int = 2,
    object_point_fraction: float = 0.5,
    overwrite: bool = False,
) -> Path:
    """Generate a synthetic scene into `out_dir` (Mip-NeRF 360 layout) and return its path. Raises
    SceneSpecError (a ValueError) for bad arguments or an existing non-empty `out_dir` without `overwrite`."""
    spec = SceneSpec(
        layout=layout,  # type: ignore[arg-type]
        num_cameras=num_cameras,
        width=width,
        height=height,
        num_rings=num_rings,
        seed=seed,
        num_points=num_points,
        fov_deg=fov_deg,
        supersample=supersample,
        object_point_fraction=object_point_fraction,
    )
    return generate(spec, Path(out_dir), overwrite=overwrite)


@dataclass
class MakeScene(SceneSpec):
    """Generate the embedded synthetic 360-degree scene (images, COLMAP model, ground truth)."""

    out: Optional[Path] = None
    """Output folder (default: outputs/scenes/<layout>-seed<seed>)."""
    overwrite: bool = False
    """Replace the output folder if it exists and is not empty."""

    def main(self) -> None:
        out = self.out if self.out is not None else Path("outputs/scenes") / f"{self.layout}-seed{self.seed}"
        spec = SceneSpec(**{k: getattr(self, k) for k in SceneSpec.__dataclass_fields__})
        start = time.perf_counter()
        try:
            path = generate(spec, out, overwrite=self.overwrite)
        except SceneSpecError as err:
            raise UserError(f"hpgs make-scene: {err}") from None
        truth = json.loads((path / "ground_truth.json").read_text())
        hidden = ", ".join(f"{h['name']} (seen by {len(h['seen_by'])}/{self.num_cameras})" for h in truth["hidden"])
        print(
            f"wrote {path}: {self.num_cameras} images {self.width}x{self.height}, {truth['num_points3D']} points, "
            f"layout {self.layout}, seed {self.seed}" + (f"; hidden: {hidden}" if hidden else "")
            + f" ({time.perf_counter() - start:.1f} s)"
        )
