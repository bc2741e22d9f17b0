"""The objects M2 works on: one table of world-space meshes with §4's feasibility.

An M2 object is a cluster of §4 (or a scene object used directly, as the paper does with its
forest of compact objects). :class:`BoardObjects` holds every object's level-0 geometry
concatenated (float32 world positions and normals (V, 3), uint8 RGBA colours (V, 4), uint32
absolute indices, object i owning ``indices[index_offset[i]:index_offset[i+1]]``), its box,
bounding sphere and triangle count, and the §4 status (feasible, too large, too few
triangles) with the near-zone range d_nz and cluster side sl_c it was classified with.

Every rank builds the same table from the same scene and parameters (deterministic), so object
ids agree between the visualization rank and the backends without any message.
"""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import parse_qsl

import numpy as np

from ..core.errors import ConfigError
from ..data.generators import generate_objects
from ..lod.clusters import FEASIBLE, ClusterParams, cluster_scene

__all__ = ["BoardObjects", "open_board_objects"]


@dataclass
class BoardObjects:
    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    indices: np.ndarray
    index_offset: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    triangles: np.ndarray
    status: np.ndarray
    d_nz: float
    sl_c: float

    @property
    def count(self) -> int:
        return len(self.triangles)

    @property
    def feasible(self) -> np.ndarray:
        return self.status == FEASIBLE

    @property
    def centers(self) -> np.ndarray:
        return (self.box_lo + self.box_hi) / 2

    @property
    def radii(self) -> np.ndarray:
        return np.linalg.norm(self.box_hi - self.box_lo, axis=1) / 2

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.box_lo.min(axis=0), self.box_hi.max(axis=0)

    def mesh(self, i: int):
        """Object ``i`` alone: ``(positions, normals, colors, indices)`` with local indices."""
        idx = self.indices[self.index_offset[i]:self.index_offset[i + 1]]
        used, local = np.unique(idx, return_inverse=True)
        return self.positions[used], self.normals[used], self.colors[used], local.astype(np.uint32)


def _from_object_scene(scene, params: ClusterParams) -> BoardObjects:
    cl = cluster_scene(scene.box_lo, scene.box_hi, scene.triangles, params, merge=False)
    return BoardObjects(scene.positions, scene.normals, scene.colors, scene.indices, np.asarray(scene.index_offset, np.int64),
                        np.asarray(scene.box_lo, np.float64), np.asarray(scene.box_hi, np.float64),
                        np.asarray(scene.triangles, np.int64), cl.status, cl.d_nz, cl.sl_c)


def open_board_objects(spec: str, params: ClusterParams) -> BoardObjects:
    """The M2 object table of a scene: ``builtin:objects[?n=..&seed=..]`` (objects used
    directly, classified by §4's rules)."""
    if spec.startswith("builtin:objects"):
        q = dict(parse_qsl(spec.partition("?")[2]))
        unknown = set(q) - {"n", "seed"}
        if unknown:
            raise ConfigError(f"scene {spec!r}: unknown parameter(s) {', '.join(sorted(unknown))}; builtin:objects takes n and seed")
        try:
            n, seed = int(q.get("n", 3000)), int(q.get("seed", 7))
        except ValueError:
            raise ConfigError(f"scene {spec!r}: n and seed must be integers") from None
        return _from_object_scene(generate_objects(n, seed), params)
    raise ConfigError(f"scene {spec!r}: the reliefboards system takes builtin:objects[?n=..&seed=..] "
                      "(scene stores once `massview prepare reliefboards` has clustered them)")
