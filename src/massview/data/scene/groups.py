"""The culling hierarchy of a scene: groups from object paths, or from a spatial k-d split.

A *path* is an object's position in a hierarchy, one integer per depth (a plant copy, its
section, its unit, ...: the source scene graph of the massive-model papers with geometry
replaced by boxes). Every distinct prefix of a path is a group; a group's box is the union of
the boxes of the objects beneath it. Scenes without a hierarchy get one by recursive median
splits of the object centres along the longest axis of their box (a k-d tree, ``leaf`` objects
per leaf at most), so any scene culls hierarchically.
"""

from __future__ import annotations

import numpy as np

from .store import GroupTree

__all__ = ["build_groups", "kd_paths", "object_order_by_kd"]


def kd_paths(center: np.ndarray, leaf: int = 16) -> np.ndarray:
    """Paths (n, D) i4 of a k-d tree over ``center`` (n, 3): 0/1 per split, D = depth needed
    for ``leaf`` objects per leaf; deterministic (stable sorts)."""
    n = len(center)
    depth = max(0, int(np.ceil(np.log2(max(n, 1) / leaf)))) if n > leaf else 0
    paths = np.zeros((n, max(depth, 1)), np.int32)
    stack = [(np.arange(n), 0)]
    while stack:
        idx, d = stack.pop()
        if d >= depth or len(idx) <= 1:
            continue
        c = center[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        order = idx[np.argsort(c[:, axis], kind="stable")]
        half = len(order) // 2
        paths[order[half:], d] = 1
        stack.append((order[:half], d + 1))
        stack.append((order[half:], d + 1))
    return paths


def object_order_by_kd(center: np.ndarray) -> np.ndarray:
    """A spatially coherent order of objects: lexicographic by k-d path."""
    p = kd_paths(center, leaf=1)
    return np.lexsort(p.T[::-1])


def build_groups(paths: np.ndarray, box_lo: np.ndarray, box_hi: np.ndarray) -> tuple[GroupTree, np.ndarray]:
    """Groups of every path prefix (depth 1..D) under one root group (depth 0).

    paths (n, D) i4, box_lo/box_hi (n, 3) f8 world. Returns the tree (parents before children,
    ordered by depth then by path) and each object's leaf group (n,) i4."""
    n, D = paths.shape
    parent, depth = [np.array([-1], np.int32)], [np.zeros(1, np.int16)]
    prev = np.zeros(n, np.int64)  # group of each object at the previous depth (root = 0)
    count = 1
    for d in range(1, D + 1):
        key = np.concatenate([prev[:, None], paths[:, d - 1: d].astype(np.int64)], axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        parent.append(uniq[:, 0].astype(np.int32))
        depth.append(np.full(len(uniq), d, np.int16))
        prev = inv + count
        count += len(uniq)
    parent = np.concatenate(parent)
    depth = np.concatenate(depth)
    lo = np.full((count, 3), np.inf)
    hi = np.full((count, 3), -np.inf)
    leaf = prev.astype(np.int32)
    for c in range(3):
        lo[:, c] = _reduce(np.minimum, leaf, box_lo[:, c], count, np.inf)
        hi[:, c] = _reduce(np.maximum, leaf, box_hi[:, c], count, -np.inf)
    for d in range(D, 0, -1):  # fold each depth into its parents, deepest first
        sel = np.nonzero(depth == d)[0]
        np.minimum.at(lo, parent[sel], lo[sel])
        np.maximum.at(hi, parent[sel], hi[sel])
    return GroupTree(parent=parent, box_lo=lo, box_hi=hi, depth=depth), leaf


def _reduce(op, idx: np.ndarray, val: np.ndarray, size: int, fill: float) -> np.ndarray:
    out = np.full(size, fill)
    op.at(out, idx, val)
    return out
