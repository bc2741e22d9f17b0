"""Scenes for the massive-model system: a scene store, or ``builtin:objects`` seen as one.

The M1 system reads a scene through the scene store's interface: ``skeleton`` (per object:
``center``, ``radius``, ``box_lo``, ``box_hi`` world units; ``levels``; ``triangles`` and
``level_error`` per level; ``occluder`` flags; ``geometry`` id; ``transform`` 4×4),
``groups`` (the group tree for hierarchical culling), ``get_mesh(geometry, level)`` and
``bounds``. :class:`BuiltinObjectStore` presents the built-in object field that way (one
level per object, identity transforms; the largest tenth of the boxes by volume are the
potential occluders), so the system runs without a prepared store.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data.scene import Mesh, SceneStore, Skeleton
from ..lod.scene import build_group_tree

__all__ = ["BuiltinObjectStore", "open_scene"]


class BuiltinObjectStore:
    """``builtin:objects[?n=..&seed=..]`` with the scene store's read interface."""

    def __init__(self, spec: str = "builtin:objects"):
        from .objects import ObjectsSystem

        s = self.scene = ObjectsSystem(spec).scene
        n = s.count
        lo, hi = s.box_lo, s.box_hi
        vol = np.prod(hi - lo, axis=1)
        occ = vol >= np.quantile(vol, 0.9) if n else np.zeros(0, bool)
        self.groups, leaf = build_group_tree(lo, hi, leaf_size=16)
        v0 = np.array([s.indices[a:b].min() if b > a else 0 for a, b in zip(s.index_offset[:-1], s.index_offset[1:])], np.int64)
        v1 = np.array([s.indices[a:b].max() + 1 if b > a else 0 for a, b in zip(s.index_offset[:-1], s.index_offset[1:])], np.int64)
        self._vrange = np.stack([v0, v1], 1)
        tri = s.triangles.reshape(n, 1).astype(np.int64)
        vbytes = (v1 - v0) * 24 + tri[:, 0] * 12
        self.skeleton = Skeleton(s.centers, s.radii, lo, hi, np.ones(n, np.int8), tri, np.zeros((n, 1), np.float32),
                                  vbytes.reshape(n, 1), occ, leaf, np.arange(n, dtype=np.int32), np.tile(np.eye(4), (n, 1, 1)))
        self.path = spec
        self.attrs = {"format": "builtin"}

    @property
    def bounds(self):
        return self.scene.bounds

    def get_mesh(self, geometry: int, level: int = 0) -> Mesh:
        s = self.scene
        a, b = s.index_offset[geometry], s.index_offset[geometry + 1]
        v0, v1 = self._vrange[geometry]
        return Mesh(s.positions[v0:v1], s.normals[v0:v1], s.colors[v0:v1], (s.indices[a:b].astype(np.int64) - v0).astype(np.uint32))


def open_scene(spec: str):
    """A scene store folder or ``builtin:objects[...]`` as a store-like object."""
    if spec.startswith("builtin:objects"):
        return BuiltinObjectStore(spec)
    return SceneStore(Path(spec))
