"""Vertex normals split at creases, for meshes whose file brings no normals.

Averaging the face normals of every face round a vertex rounds off hard edges: a box looks
like a pillar. As common mesh tools do (an auto-smooth / crease angle), the faces round a
vertex are split into *smoothing groups*: two faces that share an edge belong to one group
when their normals differ by at most ``angle`` degrees; a vertex is duplicated once per group
it touches, and each copy gets the area-weighted normal of its group's faces. Adjacency is by
position (vertices at one place that differ only in colour still smooth together), so a
finely tessellated curved surface stays smooth and a cube gets one flat normal per face.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CREASE_ANGLE", "crease_split", "weld"]

CREASE_ANGLE = 50.0  # degrees: hexagonal prisms (60°) and boxes are faceted, octagons (45°) and finer smooth


def weld(p: np.ndarray) -> np.ndarray:
    """(v,) i8: the same id for vertices at the same position (``np.unique(p, axis=0,
    return_inverse=True)``'s ids, in its order, ~3× faster: a lexsort of the columns)."""
    if len(p) == 0:
        return np.zeros(0, np.int64)
    o = np.lexsort((p[:, 2], p[:, 1], p[:, 0]))
    ps = p[o]
    ids = np.empty(len(p), np.int64)
    ids[o] = np.cumsum(np.concatenate([[False], np.any(ps[1:] != ps[:-1], axis=1)]))
    return ids


def crease_split(p: np.ndarray, tri: np.ndarray, angle: float = CREASE_ANGLE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source vertex (v',) i8, unit normals f32 (v',3), triangles (t,3) i8 into the new
    vertices) of the mesh (p (v,3), tri (t,3)) with normals split at edges sharper than
    ``angle`` degrees. New vertices are numbered in order of first use by the triangles."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tri = np.asarray(tri, np.int64).reshape(-1, 3)
    t = len(tri)
    if t == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.float32), tri
    p = np.asarray(p, np.float64)
    fn = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])  # twice the area, area-weighted
    ln = np.linalg.norm(fn, axis=1)
    un = fn / np.maximum(ln, 1e-300)[:, None]
    flat = ln <= 0  # degenerate faces take any neighbour's group (they weigh nothing)
    w = weld(p)[tri]
    # every edge of every face: welded ends (a, b) and the corners (3k+i) holding them
    i0, i1 = np.array([0, 1, 2]), np.array([1, 2, 0])
    ea, eb = w[:, i0].ravel(), w[:, i1].ravel()
    ca = (np.arange(t)[:, None] * 3 + i0).ravel()
    cb = (np.arange(t)[:, None] * 3 + i1).ravel()
    face = np.repeat(np.arange(t), 3)
    lo, hi = np.minimum(ea, eb), np.maximum(ea, eb)
    order = np.argsort(lo * (int(w.max()) + 1) + hi, kind="stable")  # (one int64 key: faster than lexsort((hi, lo)), same order)
    same = (lo[order][1:] == lo[order][:-1]) & (hi[order][1:] == hi[order][:-1])
    e1, e2 = order[:-1][same], order[1:][same]  # consecutive uses of one edge (2 on a manifold)
    f1, f2 = face[e1], face[e2]
    smooth = ((un[f1] * un[f2]).sum(axis=1) >= np.cos(np.radians(angle))) | flat[f1] | flat[f2]
    e1, e2 = e1[smooth], e2[smooth]
    direct = ea[e1] == ea[e2]  # both faces walk the edge the same way (else: opposite ways)
    u = np.concatenate([ca[e1], cb[e1]])
    v = np.concatenate([np.where(direct, ca[e2], cb[e2]), np.where(direct, cb[e2], ca[e2])])
    g = coo_matrix((np.ones(len(u), np.int8), (u, v)), shape=(3 * t, 3 * t))
    _, group = connected_components(g, directed=False)
    vert = tri.ravel()
    key = group.astype(np.int64) * (int(vert.max()) + 1) + vert
    _, first, inv = np.unique(key, return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    new = rank[inv.reshape(-1)]
    src = np.empty(len(first), np.int64)
    src[new] = vert
    n = np.zeros((len(first), 3))
    for c in range(3):
        n[:, c] = np.bincount(new, fn[np.repeat(np.arange(t), 3), c], len(first))
    nl = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(nl > 1e-300, n / np.maximum(nl, 1e-300), [0.0, 0.0, 1.0])
    return src, n.astype(np.float32), new.reshape(t, 3)
