"""An in-memory scene shaped like ``SceneStore`` (skeleton, groups, get_mesh), for tests of the
scene renderer that must not depend on the store's on-disk format. Levels are real coarser
meshes: the template tessellated at half the resolution per level."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from massview.data.generators.objects import _superquadric, _vertex_normals
from massview.lod.scene import build_group_tree


@dataclass
class Mesh:
    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    indices: np.ndarray


@dataclass
class Skeleton:
    center: np.ndarray
    radius: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    levels: np.ndarray
    triangles: np.ndarray
    level_error: np.ndarray
    level_bytes: np.ndarray
    occluder: np.ndarray
    group: np.ndarray
    geometry: np.ndarray
    transform: np.ndarray


class MemoryScene:
    def __init__(self, side: int = 6, seed: int = 3, lmax: int = 3, spacing: float = 4.0):
        rng = np.random.default_rng(seed)
        n = side * side
        self.meshes: dict[tuple[int, int], Mesh] = {}
        tris = np.zeros((n, lmax), np.int64)
        err = np.zeros((n, lmax), np.float32)
        lo, hi = np.zeros((n, 3)), np.zeros((n, 3))
        tf = np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
        for i in range(n):
            e1, e2 = rng.uniform(0.2, 1.5, 2)
            scale = rng.uniform(0.6, 1.5)
            rgb = rng.integers(60, 255, 3)
            for lv in range(lmax):
                p, t = _superquadric(max(24 >> lv, 3), max(40 >> lv, 4), e1, e2)
                p = p * scale
                nrm = _vertex_normals(p, t)
                col = np.tile(np.append(rgb, 255).astype(np.uint8), (len(p), 1))
                self.meshes[(i, lv)] = Mesh(p.astype(np.float32), nrm.astype(np.float32), col, t.astype(np.uint32))
                tris[i, lv] = len(t)
                err[i, lv] = 0.0 if lv == 0 else scale * 0.05 * 4**lv
            x, y = (i % side) * spacing, (i // side) * spacing
            tf[i, :3, 3] = (x, y, scale)
            lo[i] = tf[i, :3, 3] - scale
            hi[i] = tf[i, :3, 3] + scale
        group_tree, leaf = build_group_tree(lo, hi, leaf_size=4)
        self.groups = group_tree
        self.skeleton = Skeleton((lo + hi) / 2, np.full(n, math.sqrt(3)) * (hi - lo)[:, 0] / 2, lo, hi,
                                 np.full(n, lmax, np.int8), tris, err, tris * 40, np.zeros(n, bool), leaf,
                                 np.arange(n, dtype=np.int32), tf)
        self.path = "memory"
        self.attrs = {}

    @property
    def bounds(self):
        return self.skeleton.box_lo.min(0), self.skeleton.box_hi.max(0)

    def get_mesh(self, geometry_id: int, level: int) -> Mesh:
        return self.meshes[(geometry_id, level)]
