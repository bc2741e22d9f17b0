"""LOD levels of one object by quadric-error simplification, with each level's geometric error.

Level 0 is the object as given. Level l+1 is level l simplified to half its triangles by
quadric edge collapse (Garland & Heckbert 1997) through a registry package:
``fast-simplification`` (default) or ``pyfqmr`` — both wrap Sp4cerat's Fast-Quadric-Mesh-
Simplification; ``massview bench scene-ingest`` measures the two. Levels stop when a halving
no longer removes 20 % of the triangles or fewer than ``min_triangles`` would remain.

Borders are locked (both packages' ``preserve_border``): an object cut from a larger surface
keeps its cut as the same polyline at every level, so neighbouring objects drawn at any mix of
levels meet without cracks (simplified freely, the background showed through hairlines along
the cuts); an open mesh keeps its outline too. Where the locked outline stops a halving (it
would keep more than 80 % of the triangles: an open mesh whose border is most of it), that
level is simplified freely instead, as before, so such meshes still get their coarse levels.

Colours of the new vertices are those of the nearest level-0 vertex; normals are recomputed
from the simplified surface. With ``crease`` (a mesh whose file brought no normals), every
level's normals are split at edges sharper than ``crease`` degrees (:mod:`.normals`): the
levels are simplified from the welded surface and split afterwards, so the simplifier never
sees the hard edges as borders. A level's error is the symmetric Hausdorff distance between
it and level 0, estimated on the vertices (each vertex's exact distance to the nearest of the
4 triangles whose centroids are nearest; at most 1024 vertices, evenly strided), made non-decreasing over the levels, plus the
16-bit quantization step — the renderer picks a level from its projected size in pixels.
"""

from __future__ import annotations

import numpy as np

from .mesh import Mesh, quantization_error, vertex_normals
from .normals import crease_split

__all__ = ["build_levels", "is_closed", "simplify_once", "BACKENDS", "surface_distance", "surface_index"]

BACKENDS = ("fast-simplification", "pyfqmr")
_SAMPLES = 1024


def is_closed(indices: np.ndarray, positions: np.ndarray | None = None) -> bool:
    """True when every edge is shared by exactly two triangles (a closed 2-manifold surface);
    with ``positions``, vertices at equal positions count as one (split normals, hard edges)."""
    if len(indices) == 0:
        return False
    if positions is not None:
        p = np.asarray(positions, np.float64)
        tol = max(float(np.ptp(p, axis=0).max()), 1e-30) * 1e-6  # weld closer than 1e-6 of the size
        from .normals import weld

        indices = weld(np.round(p / tol))[indices]
        ok = (indices[:, 0] != indices[:, 1]) & (indices[:, 1] != indices[:, 2]) & (indices[:, 0] != indices[:, 2])
        indices = indices[ok]  # welding collapses the sliver triangles at poles and seams
        if len(indices) == 0:
            return False
    e = np.sort(np.concatenate([indices[:, [0, 1]], indices[:, [1, 2]], indices[:, [2, 0]]]).astype(np.int64), axis=1)
    key = e[:, 0] * (int(indices.max()) + 1) + e[:, 1]
    _, counts = np.unique(key, return_counts=True)
    return bool((counts == 2).all())


def simplify_once(p: np.ndarray, t: np.ndarray, target: int, backend: str = "fast-simplification",
                  lock_border: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(positions f32 (v,3), triangles i64 (t,3)) simplified to about ``target`` triangles,
    ``lock_border``: vertices on open edges stay where they are."""
    p = np.ascontiguousarray(p, np.float32)
    t = np.ascontiguousarray(t, np.int32)
    if backend == "fast-simplification":
        import fast_simplification

        q, f = fast_simplification.simplify(p, t, target_count=max(int(target), 1), preserve_border=bool(lock_border))
    elif backend == "pyfqmr":
        import pyfqmr

        s = pyfqmr.Simplify()
        s.setMesh(p, t)
        s.simplify_mesh(target_count=max(int(target), 1), aggressiveness=7, preserve_border=bool(lock_border), verbose=False)
        q, f, _ = s.getMesh()
    else:
        raise ValueError(f"unknown simplifier {backend!r}; use one of {BACKENDS}")
    return np.asarray(q, np.float32), np.asarray(f, np.int64).reshape(-1, 3)


def _point_triangle_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact distance from points x (m,3) to triangles (a, b, c) (m,3) each (Ericson, RTCD 5.1.5)."""
    ab, ac, ap = b - a, c - a, x - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = x - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = x - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        # edge/vertex regions: clamp barycentrics onto the closest feature
        s_ab = np.clip(np.where(d1 - d3 != 0, d1 / (d1 - d3), 0), 0, 1)
        s_ac = np.clip(np.where(d2 - d6 != 0, d2 / (d2 - d6), 0), 0, 1)
        s_bc = np.clip(np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0), 0, 1)
    inside = (va >= 0) & (vb >= 0) & (vc >= 0) & (v >= 0) & (w >= 0)
    q_in = a + ab * v[:, None] + ac * w[:, None]
    cands = np.stack([a + ab * s_ab[:, None], a + ac * s_ac[:, None], b + (c - b) * s_bc[:, None]])
    d_edge = np.linalg.norm(cands - x[None], axis=2).min(axis=0)
    return np.where(inside, np.linalg.norm(q_in - x, axis=1), d_edge)


def surface_index(p: np.ndarray, t: np.ndarray):
    """(triangle corners f8 (t,3,3), k-d tree of their centroids) for :func:`surface_distance`."""
    from scipy.spatial import cKDTree

    tri = p[t].astype(np.float64)
    return tri, cKDTree(tri.mean(axis=1))


def surface_distance(points: np.ndarray, p: np.ndarray, t: np.ndarray, k: int = 4, index=None) -> float:
    """Largest distance from ``points`` (m,3) to the surface (p, t), each point measured to the
    ``k`` triangles with the nearest centroids (an estimate of the one-sided Hausdorff distance).
    ``index`` may pass a prebuilt :func:`surface_index` of (p, t)."""
    if len(points) == 0 or len(t) == 0:
        return 0.0
    tri, tree = index or surface_index(p, t)
    k = min(k, len(t))
    _, nn = tree.query(points, k=k)
    nn = nn.reshape(len(points), k)
    x = np.repeat(points.astype(np.float64), k, axis=0)
    tt = tri[nn.ravel()]
    d = _point_triangle_distance(x, tt[:, 0], tt[:, 1], tt[:, 2]).reshape(-1, k).min(axis=1)
    return float(d.max())


def _sample(p: np.ndarray) -> np.ndarray:
    step = max(1, len(p) // _SAMPLES)
    return p[::step]


def _split(p: np.ndarray, colors: np.ndarray, f: np.ndarray, crease: float) -> Mesh:
    src, n, tri = crease_split(p, f, crease)
    return Mesh(np.asarray(p, np.float32)[src], n, colors[src], tri.astype(np.uint32))


def build_levels(mesh: Mesh, max_levels: int = 8, min_triangles: int = 64, backend: str = "fast-simplification",
                 crease: float | None = None, free_border: bool = True) -> tuple[list[Mesh], list[float]]:
    """Level meshes (level 0 = ``mesh`` itself) and their errors (object units, level 0: 0.0).
    With ``crease`` (degrees), ``mesh.normals`` are ignored and every level gets normals split
    at edges sharper than that (level 0 = ``mesh`` with vertices duplicated along them).
    Every level keeps the open border (its vertices stay where they are); where that stops a
    halving, ``free_border`` halves it with the border free, else the levels end there (a piece
    cut from a larger surface: its neighbours share the border, which must stay the same polyline
    at every level, or neighbours drawn at different levels would show cracks between them)."""
    from scipy.spatial import cKDTree

    levels, errors = [mesh if crease is None else _split(mesh.positions, mesh.colors, mesh.indices, crease)], [0.0]
    if mesh.triangle_count == 0:
        return levels, errors
    p0 = mesh.positions.astype(np.float64)
    lo, hi = p0.min(axis=0), p0.max(axis=0)
    qerr = quantization_error(lo, hi)
    tree = index0 = None
    p, t = mesh.positions, mesh.indices.astype(np.int64)
    while len(levels) < max_levels:
        target = len(t) // 2
        if target < min_triangles:
            break
        q, f = simplify_once(p, t, target, backend)
        if len(f) > 0.8 * len(t) and free_border:  # the locked outline holds it (an open mesh with a long border): halve it freely
            q, f = simplify_once(p, t, target, backend, lock_border=False)
        if len(f) == 0 or len(f) > 0.8 * len(t):
            break
        tree = tree or cKDTree(p0)
        _, near = tree.query(q)
        index0 = index0 or surface_index(mesh.positions, mesh.indices.astype(np.int64))
        err = max(surface_distance(_sample(p0), q, f), surface_distance(_sample(q), mesh.positions, mesh.indices, index=index0))
        errors.append(max(errors[-1], err + qerr))
        levels.append(Mesh(q, vertex_normals(q, f), mesh.colors[near], f.astype(np.uint32)) if crease is None
                      else _split(q, mesh.colors[near], f, crease))
        p, t = q, f
    return levels, errors
