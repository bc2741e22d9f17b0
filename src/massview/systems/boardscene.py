"""The objects M2 works on: a table of world-space meshes with §4's feasibility.

An M2 object is a cluster of §4 (``massview prepare reliefboards`` stores the clustering in a
scene store), or a scene object used directly, as the paper does with its forest of compact
objects. :class:`BoardObjects` holds per object its box, triangle count and §4 status
(feasible, too large, too few triangles) with the near-zone range d_nz and cluster side sl_c it
was classified with, and loads an object's level-0 geometry on demand: ``mesh(i) -> (positions
(V, 3) float32, normals (V, 3) float32, colours (V, 4) uint8, indices (3T,) uint32)``, positions
in world axes relative to ``origins[i]`` (float64; a store's M2 object: its box centre). The
visualization rank concatenates all of them relative to one ``origin`` (the scene's box
centre) and draws them with ``mvp · translate(origin)`` formed in float64; a backend loads only
the objects it holds replicas of and captures each with ``view · translate(origins[i])``; a
board's vertices are relative to its centre. So float32 only ever holds coordinates relative to
a nearby point — as M1 draws each object camera-relative — and a scene stored at UTM-like
coordinates (the scene store keeps float32 local frames with float64 transforms) gives the
same boards and frames as at the origin.

Every rank builds the same table from the same scene and parameters (deterministic), so object
ids agree between the visualization rank and the backends without any message.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable
from urllib.parse import parse_qsl

import numpy as np

from ..core.errors import ConfigError, SceneNotFoundError
from ..data.board_clusters import read_clusters
from ..data.generators import generate_objects
from ..lod.clusters import FEASIBLE, ClusterParams, cluster_scene

__all__ = ["BoardObjects", "open_board_objects", "open_scene_store", "objects_from_scene", "objects_from_store"]


@dataclass
class BoardObjects:
    box_lo: np.ndarray
    box_hi: np.ndarray
    triangles: np.ndarray
    status: np.ndarray
    d_nz: float
    sl_c: float
    loader: Callable[[int], tuple] = field(repr=False)
    _all: tuple | None = field(default=None, repr=False)
    origins: np.ndarray | None = field(default=None, repr=False)  # (n, 3) f8: object i's mesh is relative to origins[i]
    origin: np.ndarray | None = field(default=None, repr=False)  # (3,) f8: concatenated() positions are relative to it

    def __post_init__(self) -> None:
        self.origins = np.zeros((self.count, 3)) if self.origins is None else np.asarray(self.origins, np.float64)
        self.origin = np.zeros(3) if self.origin is None else np.asarray(self.origin, np.float64)

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

    @property
    def obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        """The objects' boxes, which the ``walkthrough`` path walks round."""
        return self.box_lo, self.box_hi

    def mesh(self, i: int) -> tuple:
        """Object ``i``'s level 0: positions f32 (V, 3) in world axes relative to
        ``origins[i]``, world normals f32 (V, 3), colours u8 (V, 4), indices u32 (3T,)."""
        return self.loader(int(i))

    def concatenated(self) -> tuple:
        """``(positions, normals, colors, indices, index_offset, origin)`` of every object, the
        positions f32 relative to ``origin`` (f8; :class:`~massview.render.meshes.MeshRenderer`
        takes the tuple as it is), object i owning ``indices[index_offset[i]:index_offset[i+1]]``
        (absolute vertex indices)."""
        if self._all is None:
            parts = [self.mesh(i) for i in range(self.count)]
            base = np.concatenate([[0], np.cumsum([len(p[0]) for p in parts])[:-1]]).astype(np.int64)
            offs = np.concatenate([[0], np.cumsum([len(p[3]) for p in parts])]).astype(np.int64)
            shift = self.origins - self.origin
            pos = [p[0] if not shift[i].any() else (p[0].astype(np.float64) + shift[i]).astype(np.float32) for i, p in enumerate(parts)]
            self._all = (np.concatenate(pos).astype(np.float32), np.concatenate([p[1] for p in parts]).astype(np.float32),
                         np.concatenate([p[2] for p in parts]).astype(np.uint8),
                         np.concatenate([p[3].astype(np.int64) + b for p, b in zip(parts, base)]).astype(np.uint32), offs)
        return (*self._all, self.origin)


def objects_from_scene(scene, params: ClusterParams) -> BoardObjects:
    """A generated :class:`~massview.data.generators.objects.ObjectScene`, objects used directly
    (its positions are world coordinates near the origin: origins zero)."""
    cl = cluster_scene(scene.box_lo, scene.box_hi, scene.triangles, params, merge=False)
    offs = np.asarray(scene.index_offset, np.int64)

    def load(i):
        idx = scene.indices[offs[i]:offs[i + 1]]
        used, local = np.unique(idx, return_inverse=True)
        return scene.positions[used], scene.normals[used], scene.colors[used], local.astype(np.uint32)

    return BoardObjects(np.asarray(scene.box_lo, np.float64), np.asarray(scene.box_hi, np.float64),
                        np.asarray(scene.triangles, np.int64), cl.status, cl.d_nz, cl.sl_c, load,
                        (scene.positions, scene.normals, scene.colors, scene.indices, offs))


def _placed_mesh(store, obj: int, origin: np.ndarray) -> tuple:
    """Level 0 of one store object placed by its float64 transform (positions relative to
    ``origin``, computed in float64 and only then cast to float32, so an object at UTM-like
    coordinates keeps the precision of its stored local frame; normals through the inverse
    transpose)."""
    sk = store.skeleton
    m = store.get_mesh(int(sk.geometry[obj]), 0)
    t = np.asarray(sk.transform[obj], np.float64)
    lin = t[:3, :3]
    pos = np.asarray(m.positions, np.float64) @ lin.T + (t[:3, 3] - origin)
    nrm = np.asarray(m.normals, np.float64) @ np.linalg.inv(lin)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    return pos.astype(np.float32), nrm.astype(np.float32), np.asarray(m.colors, np.uint8), np.asarray(m.indices, np.uint32).reshape(-1)


def objects_from_store(store, params: ClusterParams, labels: np.ndarray | None = None,
                       status: np.ndarray | None = None, attrs: dict | None = None) -> BoardObjects:
    """A scene store (``skeleton`` with ``box_lo``, ``box_hi``, ``triangles`` (n, levels),
    ``geometry``, ``transform``; ``get_mesh(geometry, level)``). With ``labels`` (cluster id per
    store object) and ``status``/``attrs`` (per cluster, d_nz and sl_c) from ``prepare
    reliefboards``, the M2 objects are the stored clusters; without, every store object is used
    directly, classified for ``params``."""
    sk = store.skeleton
    lo, hi = np.asarray(sk.box_lo, np.float64), np.asarray(sk.box_hi, np.float64)
    tris = np.asarray(sk.triangles, np.int64)
    tris = tris[:, 0] if tris.ndim == 2 else tris
    if labels is None:
        labels = np.arange(len(tris))
    labels = np.asarray(labels, np.int64)
    if labels.shape != tris.shape or labels.min(initial=0) < 0:
        raise ConfigError(f"{getattr(store, 'path', 'scene')}: reliefboard cluster labels do not match its {len(tris)} objects; "
                          "run `massview prepare reliefboards` again")
    m = int(labels.max(initial=-1)) + 1
    c_lo, c_hi = np.full((m, 3), np.inf), np.full((m, 3), -np.inf)
    np.minimum.at(c_lo, labels, lo)
    np.maximum.at(c_hi, labels, hi)
    c_tris = np.bincount(labels, weights=tris, minlength=m).astype(np.int64)
    if status is None:
        cl = cluster_scene(c_lo, c_hi, c_tris, params, merge=False)
        status, d_nz, sl_c = cl.status, cl.d_nz, cl.sl_c
    else:
        status, d_nz, sl_c = np.asarray(status, np.int8), float(attrs["d_nz"]), float(attrs["sl_c"])
    members = [np.flatnonzero(labels == c) for c in range(m)]
    origins = (c_lo + c_hi) / 2  # each M2 object's mesh about its box centre ...
    scene_lo, scene_hi = lo.min(axis=0, initial=np.inf), hi.max(axis=0, initial=-np.inf)
    origin = (scene_lo + scene_hi) / 2 if len(lo) else np.zeros(3)  # ... and the visualization rank's buffer about the scene's

    def load(c):
        parts = [_placed_mesh(store, o, origins[c]) for o in members[c]]
        base = np.concatenate([[0], np.cumsum([len(p[0]) for p in parts])[:-1]])
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts]),
                np.concatenate([p[3].astype(np.int64) + b for p, b in zip(parts, base)]).astype(np.uint32))

    return BoardObjects(c_lo, c_hi, c_tris, status, d_nz, sl_c, load, origins=origins, origin=origin)


def open_board_objects(spec: str, params: ClusterParams) -> BoardObjects:
    """The M2 object table of a scene: ``builtin:objects[?n=..&seed=..]`` (objects used
    directly, classified by §4's rules) or a scene store (its clusters when prepared)."""
    if spec.startswith("builtin:objects"):
        q = dict(parse_qsl(spec.partition("?")[2]))
        unknown = set(q) - {"n", "seed"}
        if unknown:
            raise ConfigError(f"scene {spec!r}: unknown parameter(s) {', '.join(sorted(unknown))}; builtin:objects takes n and seed")
        try:
            n, seed = int(q.get("n", 3000)), int(q.get("seed", 7))
        except ValueError:
            raise ConfigError(f"scene {spec!r}: n and seed must be integers") from None
        return objects_from_scene(generate_objects(n, seed), params)
    store = open_scene_store(spec)
    stored = read_clusters(spec)
    if stored is None:
        return objects_from_store(store, params)
    return objects_from_store(store, params, stored.labels, stored.status, stored.attrs)


def open_scene_store(spec: str):
    """The scene store at ``spec`` (SceneNotFoundError naming what to give otherwise)."""
    from pathlib import Path

    if not (Path(spec) / "zarr.json").exists():
        raise SceneNotFoundError(f"scene {spec!r} not found: the reliefboards system takes builtin:objects[?n=..&seed=..] "
                                 "or a scene store (make one with `massview generate scene` or `massview prepare scene`)")
    try:
        from ..data.scene import SceneStore
    except ImportError:
        raise SceneNotFoundError(f"scene {spec!r}: this massview has no scene-store support") from None
    return SceneStore(spec)
