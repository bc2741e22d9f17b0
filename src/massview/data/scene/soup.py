"""Splitting an unstructured triangle soup into objects (Reliefboards paper §4, first phase).

The soup is cut into spatial *cells* of about ``cell_triangles`` triangles (a grid over the
bounds; a triangle belongs to the cell of its centroid) so that a soup larger than memory is
handled one cell at a time — the in-memory and the streamed ingest both go through
:func:`cell_objects` with the same cells, so they write the same store. Inside a cell:

A cell much denser than the average is halved further (:func:`split_dense`). Then:

1. remove redundant vertices (equal position, colour and normal) and faces (degenerate, or
   the same three vertices as an earlier face);
2. connected components (vertices welded by position);
3. agglomerative clustering as in the paper: components are the base clusters; repeatedly
   join the pair whose joined axis-aligned box has the smallest longest side, among each
   cluster's 8 nearest neighbours only (the paper's optimisation), while the joined cluster
   stays within ``object_triangles`` triangles and ``object_size`` longest side. A component
   larger than ``object_triangles`` is cut into pieces by a k-d split of its triangles.

Objects come out in a spatially coherent, deterministic order.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Corners", "SplitParams", "cell_grid", "cell_of", "clean_soup", "clean_mesh", "cell_objects", "split_dense"]


@dataclass(frozen=True)
class SplitParams:
    object_triangles: int = 16384  # largest object a cluster may grow to
    object_size: float = math.inf  # largest longest box side of a joined cluster (world units)
    cell_triangles: int = 1 << 18  # triangles per spatial cell (memory bound of one cell)


@dataclass(frozen=True)
class Corners:
    """A soup as triangle corners: positions f8 (m,3,3) (absolute: float64 keeps georeferenced
    coordinates), colours u8 (m,3,4), normals f32 (m,3,3) or None."""

    positions: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None

    @property
    def count(self) -> int:
        return len(self.positions)


def cell_grid(lo: np.ndarray, hi: np.ndarray, triangles: int, cell_triangles: int) -> np.ndarray:
    """Cells per axis (3,) i8: about triangles / cell_triangles cells, shaped like the box."""
    n = max(1, math.ceil(triangles / cell_triangles))
    ext = np.maximum(np.asarray(hi, float) - np.asarray(lo, float), 1e-12)
    dims = np.ones(3, np.int64)
    while dims.prod() < n:  # split the axis whose cells are longest
        k = int(np.argmax(ext / dims))
        dims[k] += 1
    return dims


def cell_of(centroid: np.ndarray, lo: np.ndarray, hi: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """Cell index (m,) i8 of triangle centroids (m,3) in the grid ``dims`` over [lo, hi]."""
    ext = np.maximum(np.asarray(hi, float) - np.asarray(lo, float), 1e-12)
    ijk = np.clip(((centroid - lo) / ext * dims).astype(np.int64), 0, dims - 1)
    return (ijk[:, 2] * dims[1] + ijk[:, 1]) * dims[0] + ijk[:, 0]


def split_dense(c: Corners, limit: int) -> list[Corners]:
    """A cell of more than 2 x ``limit`` triangles (dense data in a uniform grid) cut in halves
    at the median centroid along its longest axis, recursively, so no piece processed at once
    exceeds the memory of a regular cell. Deterministic, order-keeping within each half."""
    if c.count <= 2 * limit:
        return [c]
    cent = c.positions.astype(np.float64).mean(axis=1)
    axis = int(np.argmax(cent.max(0) - cent.min(0)))
    order = np.argsort(cent[:, axis], kind="stable")
    halves = [np.sort(order[: c.count // 2]), np.sort(order[c.count // 2:])]
    out = []
    for h in halves:
        sub = Corners(c.positions[h], c.colors[h], None if c.normals is None else c.normals[h])
        out += split_dense(sub, limit)
    return out


def _key_rows(positions: np.ndarray, colors: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
    """(n,) void keys: the bits of each row's position, colour and normal."""
    parts = [positions.reshape(-1, 3).view(np.uint32), colors.reshape(-1, 4).view(np.uint32)[:, :1]]
    if normals is not None:
        parts.append(normals.reshape(-1, 3).view(np.uint32))
    rows = np.ascontiguousarray(np.concatenate(parts, 1))
    return rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()


def _kept_faces(faces: np.ndarray) -> np.ndarray:
    """Sorted indices of the faces that are neither degenerate nor the same three vertices as
    an earlier non-degenerate face."""
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    s = np.sort(faces, axis=1)
    s[~ok] = -1
    n = int(s.max(initial=-1)) + 2  # entries + 1 lie in [0, n)
    if n ** 3 < 2 ** 63:  # the sorted triple as one int64 (its rows' order): ~9× faster than rows
        key = ((s[:, 0] + 1) * n + (s[:, 1] + 1)) * n + (s[:, 2] + 1)
        _, keep = np.unique(key, return_index=True)
    else:
        _, keep = np.unique(s, axis=0, return_index=True)
    return np.sort(keep[ok[keep]])


def _unique_bits(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_index=True, return_inverse=True)[1:]`` of (n,) void keys —
    their byte (memcmp) order, the first of equal keys — ~1.5× faster: the bytes read as
    big-endian 64-bit words (whose numeric order is the bytes' order) and lexsorted."""
    if len(keys) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    b = keys.view(np.uint8).reshape(len(keys), -1)
    if b.shape[1] % 8:
        b = np.concatenate([b, np.zeros((len(b), 8 - b.shape[1] % 8), np.uint8)], 1)
    words = np.ascontiguousarray(b).view(">u8").astype(np.uint64)
    order = np.lexsort(words.T[::-1])  # stable: equal keys keep their input order
    w = words[order]
    start = np.empty(len(order), bool)
    start[0] = True
    start[1:] = (w[1:] != w[:-1]).any(1)
    inv = np.empty(len(order), np.intp)
    inv[order] = np.cumsum(start) - 1
    return order[start], inv


def clean_soup(c: Corners) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Shared vertices of a corner soup: (positions (v,3) of the corners' dtype, colours u8
    (v,4), normals or None, faces i8 (t,3)), redundant vertices merged, degenerate and repeated
    faces dropped (the first occurrence is kept, in input order). Vertices are equal when their
    bits are, so float64 corners are merged (and faces found degenerate) at float64 precision.
    The vertices come in the order of their bits (``np.unique`` of the rows)."""
    first, inv = _unique_bits(_key_rows(c.positions, c.colors, c.normals))
    faces = inv.reshape(c.count, 3).astype(np.int64)
    faces = faces[_kept_faces(faces)]
    flat = lambda a, w: a.reshape(-1, w)[first]  # noqa: E731
    nrm = flat(c.normals, 3) if c.normals is not None else None
    return flat(c.positions, 3), flat(c.colors, 4), nrm, faces


def clean_mesh(p: np.ndarray, col: np.ndarray, nrm: np.ndarray | None, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """``clean_soup(Corners(p[f], col[f], nrm[f]))`` — the same vertices in the same order and
    the same faces — computed on the v vertices the faces use instead of their 3t corners (the
    second clean of an object, once in its float32 frame, where most vertices are shared)."""
    f = np.asarray(f, np.int64).reshape(-1, 3)
    used = np.zeros(len(p), bool)
    used[f] = True
    idx = np.flatnonzero(used)
    first, inv = _unique_bits(_key_rows(p[idx], col[idx], None if nrm is None else nrm[idx]))
    remap = np.zeros(len(p), np.int64)
    remap[idx] = inv.reshape(-1)
    faces = remap[f]
    faces = faces[_kept_faces(faces)]
    src = idx[first]
    return p[src], col[src], None if nrm is None else nrm[src], faces


def _components(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Component label (t,) of each face; vertices welded by position."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from .normals import weld

    f = weld(p)[faces]
    n = int(f.max()) + 1
    a = np.concatenate([f[:, 0], f[:, 1]])
    b = np.concatenate([f[:, 1], f[:, 2]])
    g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    return lab[f[:, 0]]


def _kd_pieces(cent: np.ndarray, idx: np.ndarray, cap: int) -> list[np.ndarray]:
    if len(idx) <= cap:
        return [idx]
    c = cent[idx]
    axis = int(np.argmax(c.max(0) - c.min(0)))
    order = idx[np.argsort(c[:, axis], kind="stable")]
    h = len(order) // 2
    return _kd_pieces(cent, order[:h], cap) + _kd_pieces(cent, order[h:], cap)


def _neighbours(lo: np.ndarray, hi: np.ndarray, cand: np.ndarray, n: int) -> dict[int, set]:
    """Each candidate's 8 nearest candidates by box centre (symmetric), the paper's bound on
    the joined boxes tried per cluster."""
    from scipy.spatial import cKDTree

    nbrs: dict[int, set] = {i: set() for i in range(n)}
    if len(cand) > 1:
        k = min(9, len(cand))
        _, nn = cKDTree((lo[cand] + hi[cand]) / 2).query((lo[cand] + hi[cand]) / 2, k=k)
        for a, row in zip(cand, nn.reshape(len(cand), k)):
            for b in cand[row]:
                if b != a:
                    nbrs[int(a)].add(int(b))
                    nbrs[int(b)].add(int(a))
    return nbrs


def _cluster(lo: np.ndarray, hi: np.ndarray, tris: np.ndarray, open_: np.ndarray, sp: SplitParams) -> list[list[int]]:
    """Agglomerative clustering of base clusters (boxes lo/hi (n,3), triangle counts (n,));
    only ``open_`` ones may join. Returns lists of base-cluster ids."""
    n = len(tris)
    members = {i: [i] for i in range(n)}
    box = {i: (lo[i], hi[i], int(tris[i])) for i in range(n)}
    cand = np.nonzero(open_)[0]
    heap: list = []
    nbrs = _neighbours(lo, hi, cand, n)
    alive = set(members)

    def push(a: int, b: int) -> None:
        la, ha, ta = box[a]
        lb, hb, tb = box[b]
        side = float((np.maximum(ha, hb) - np.minimum(la, lb)).max())
        if ta + tb <= sp.object_triangles and side <= sp.object_size:
            heapq.heappush(heap, (side, min(a, b), max(a, b)))

    for a in cand:
        for b in nbrs[int(a)]:
            if int(a) < b:
                push(int(a), b)
    nxt = n
    while heap:
        _, a, b = heapq.heappop(heap)
        if a not in alive or b not in alive:
            continue
        la, ha, ta = box.pop(a)
        lb, hb, tb = box.pop(b)
        alive -= {a, b}
        box[nxt] = (np.minimum(la, lb), np.maximum(ha, hb), ta + tb)
        members[nxt] = members.pop(a) + members.pop(b)
        nbrs[nxt] = (nbrs.pop(a) | nbrs.pop(b)) & alive
        alive.add(nxt)
        for c in sorted(nbrs[nxt]):
            nbrs[c].add(nxt)
            push(c, nxt)
        nxt += 1
    return [sorted(members[i]) for i in sorted(alive)]


def cell_objects(c: Corners, sp: SplitParams) -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]]:
    """Objects (positions, colours, normals or None, faces) of one cell of a soup, in a
    spatially coherent order (k-d order of their box centres)."""
    from .groups import object_order_by_kd

    p, col, nrm, faces = clean_soup(c)
    if len(faces) == 0:
        return []
    lab = _components(p, faces)
    cent = p[faces].mean(axis=1)
    base, open_ = [], []
    for comp in _split_by_label(lab):
        pieces = _kd_pieces(cent, comp, sp.object_triangles)
        base += pieces
        open_ += [len(pieces) == 1] * len(pieces)
    bid = np.empty(len(faces), np.int64)
    for i, b in enumerate(base):
        bid[b] = i
    fp = p[faces].astype(np.float64)
    lo = np.full((len(base), 3), np.inf)
    hi = np.full((len(base), 3), -np.inf)
    np.minimum.at(lo, bid, fp.min(axis=1))
    np.maximum.at(hi, bid, fp.max(axis=1))
    tris = np.bincount(bid, minlength=len(base))
    clusters = _cluster(lo, hi, tris, np.array(open_), sp)
    objs = [np.sort(np.concatenate([base[i] for i in cl])) for cl in clusters]
    centers = np.stack([(lo[cl].min(0) + hi[cl].max(0)) / 2 for cl in clusters])
    out = []
    for k in object_order_by_kd(centers):
        f = faces[objs[k]]
        used, local = np.unique(f, return_inverse=True)
        out.append((p[used], col[used], None if nrm is None else nrm[used], local.reshape(-1, 3)))
    return out


def _split_by_label(lab: np.ndarray) -> list[np.ndarray]:
    order = np.argsort(lab, kind="stable")
    cuts = np.nonzero(np.diff(lab[order]))[0] + 1
    return np.split(order, cuts)
