"""The built-in procedural scene ``builtin:objects``.

A field of shaded meshes (superquadrics and tori of varied tessellation) on a jittered grid,
deterministic for a seed. Objects lie in disjoint grid cells and never touch, so no two objects
tie in depth: sort-last compositing of any partition of the objects reproduces the serial image
exactly. Geometry is pre-transformed into one vertex array (float32 positions and normals,
RGBA8 colors) and one uint32 index array; object i owns the index range
``index_offset[i]:index_offset[i+1]`` and the skeleton arrays (bounding spheres and boxes,
triangle counts) describe it for culling and load balancing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...core.errors import ConfigError

__all__ = ["ObjectScene", "generate_objects"]


@dataclass
class ObjectScene:
    positions: np.ndarray  # (V, 3) float32, world units
    normals: np.ndarray  # (V, 3) float32, unit
    colors: np.ndarray  # (V, 4) uint8
    indices: np.ndarray  # (3T,) uint32, absolute vertex indices
    index_offset: np.ndarray  # (n+1,) int64, into ``indices``
    centers: np.ndarray  # (n, 3) float64 bounding-sphere centers
    radii: np.ndarray  # (n,) float64 bounding-sphere radii
    box_lo: np.ndarray  # (n, 3) float64
    box_hi: np.ndarray  # (n, 3) float64
    triangles: np.ndarray  # (n,) int64 triangle count per object (the load weight)

    @property
    def count(self) -> int:
        return len(self.radii)

    @property
    def total_triangles(self) -> int:
        return int(self.triangles.sum())

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.box_lo.min(axis=0), self.box_hi.max(axis=0)

    def range_items(self, a: float, b: float) -> np.ndarray:
        """Objects in database range [a, b): those whose first triangle, as a fraction of all
        triangles in object order, lies in [a, b). Ranges R_i = [i/N, (i+1)/N) partition the
        objects into contiguous runs of nearly equal triangle counts."""
        start = np.concatenate([[0], np.cumsum(self.triangles)[:-1]]) / max(self.total_triangles, 1)
        return np.nonzero((start >= a) & (start < b))[0]


def _superquadric(nu: int, nv: int, e1: float, e2: float) -> tuple[np.ndarray, np.ndarray]:
    u = np.linspace(-math.pi / 2, math.pi / 2, nu + 1)
    v = np.linspace(-math.pi, math.pi, nv + 1)
    uu, vv = np.meshgrid(u, v, indexing="ij")

    def sp(w, e):
        return np.sign(np.sin(w)) * np.abs(np.sin(w)) ** e

    def cp(w, e):
        return np.sign(np.cos(w)) * np.abs(np.cos(w)) ** e

    p = np.stack([cp(uu, e1) * cp(vv, e2), cp(uu, e1) * sp(vv, e2), sp(uu, e1)], axis=-1)
    return p.reshape(-1, 3), _grid_indices(nu, nv)


def _torus(nu: int, nv: int, r: float) -> tuple[np.ndarray, np.ndarray]:
    u = np.linspace(0, 2 * math.pi, nu + 1)
    v = np.linspace(0, 2 * math.pi, nv + 1)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    big = 1.0 - r
    p = np.stack([(big + r * np.cos(vv)) * np.cos(uu), (big + r * np.cos(vv)) * np.sin(uu), r * np.sin(vv)], axis=-1)
    return p.reshape(-1, 3), _grid_indices(nu, nv)


def _grid_indices(nu: int, nv: int) -> np.ndarray:
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * (nv + 1) + j
    b = a + nv + 1
    tri = np.stack([np.stack([a, b, a + 1], -1), np.stack([a + 1, b, b + 1], -1)], axis=-2)
    return tri.reshape(-1, 3).astype(np.int64)


def _vertex_normals(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    fn = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
    n = np.zeros_like(p)
    for k in range(3):
        np.add.at(n, tri[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    fallback = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)
    return np.where(length > 1e-12, n / np.maximum(length, 1e-12), fallback)


def _templates() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    shapes = []
    for nu, nv in ((6, 10), (8, 14), (12, 20), (16, 26), (22, 36)):
        for e1, e2 in ((1.0, 1.0), (0.3, 0.3), (0.2, 1.0), (1.6, 1.0)):
            p, t = _superquadric(nu, nv, e1, e2)
            shapes.append((p, t))
        p, t = _torus(nv, nu, 0.3)
        shapes.append((p, t))
    return [(p, t, _vertex_normals(p, t)) for p, t in shapes]


def generate_objects(count: int = 3000, seed: int = 7, spacing: float = 4.0) -> ObjectScene:
    """Generate ``count`` objects on a jittered square grid with cells of ``spacing`` units.

    About 660 triangles per object on average (3000 objects ≈ 2.0 M triangles)."""
    if count < 1:
        raise ConfigError(f"builtin:objects needs at least one object, got n={count}")
    rng = np.random.default_rng(seed)
    temps = _templates()
    side = math.ceil(math.sqrt(count))
    cell = np.arange(count)
    gx, gy = (cell % side).astype(np.float64), (cell // side).astype(np.float64)
    kind = rng.integers(0, len(temps), count)
    half = spacing / 2
    radius = rng.uniform(0.35, 0.9, count) * half * 0.9  # sphere radius inside the cell
    stretch = rng.uniform(0.5, 1.0, (count, 3))
    stretch[:, 2] = rng.uniform(0.6, 2.5, count)
    angle = rng.uniform(0, 2 * math.pi, count)
    jitter = rng.uniform(-1, 1, (count, 2)) * (half - radius[:, None] * 1.0)
    base_z = rng.uniform(0.05, 1.0, count) * spacing * 0.1
    hue = rng.uniform(0, 1, count)

    positions, normals, colors, indices, offsets = [], [], [], [], [0]
    centers = np.empty((count, 3))
    radii = np.empty(count)
    lo = np.empty((count, 3))
    hi = np.empty((count, 3))
    tri_counts = np.empty(count, np.int64)
    nvert = 0
    for i in range(count):
        p0, t0, n0 = temps[kind[i]]
        s = stretch[i] * radius[i]
        s[2] = radius[i] * stretch[i, 2] * 0.8
        c, sn = math.cos(angle[i]), math.sin(angle[i])
        rot = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1.0]])
        p = (p0 * s) @ rot.T
        # keep the object inside its cell: horizontal footprint radius ≤ radius
        foot = np.linalg.norm(p[:, :2], axis=1).max()
        if foot > radius[i]:
            p[:, :2] *= radius[i] / foot
            s[:2] *= radius[i] / foot
        p[:, 2] -= p[:, 2].min()
        p += np.array([gx[i] * spacing + half + jitter[i, 0], gy[i] * spacing + half + jitter[i, 1], base_z[i]])
        n = (n0 / s) @ rot.T
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        rgb = _hue_rgb(hue[i])
        shade = 0.75 + 0.25 * (p0[:, 2:3] + 1) / 2
        col = np.concatenate([np.clip(rgb * shade * 255, 0, 255), np.full((len(p), 1), 255)], axis=1)
        positions.append(p.astype(np.float32))
        normals.append(n.astype(np.float32))
        colors.append(col.astype(np.uint8))
        indices.append((t0 + nvert).astype(np.uint32).ravel())
        nvert += len(p)
        offsets.append(offsets[-1] + t0.size)
        lo[i], hi[i] = p.min(axis=0), p.max(axis=0)
        centers[i] = (lo[i] + hi[i]) / 2
        radii[i] = np.linalg.norm(p - centers[i], axis=1).max()
        tri_counts[i] = len(t0)
    return ObjectScene(
        positions=np.concatenate(positions),
        normals=np.concatenate(normals),
        colors=np.concatenate(colors),
        indices=np.concatenate(indices),
        index_offset=np.asarray(offsets, np.int64),
        centers=centers,
        radii=radii,
        box_lo=lo,
        box_hi=hi,
        triangles=tri_counts,
    )


def _hue_rgb(h: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h * 6) % 6
    return 1 - 0.75 * np.clip(np.minimum(k, 4 - k), 0, 1)
