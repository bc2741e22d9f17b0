"""A large binary PLY written with bounded memory: the level-0 geometry of a generated scene.

Used by ``massview bench scene-ingest`` to have a real, unstructured triangle soup of any size
on disk (a PLY keeps no objects: ingest must find them again). A PLY holds all vertices
before all faces, so the scene is walked twice — once writing vertices, once faces — one
node at a time; memory is one node's mesh whatever the file size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .scenes import copy_offsets, place_levels, scene_nodes

__all__ = ["write_scene_ply"]

_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
_FACE = np.dtype([("n", "u1"), ("i", "<i4", (3,))])


def _walk(kind: str, copies: int, size: float, seed: int):
    nodes, extent = scene_nodes(kind, size, seed)
    offsets = copy_offsets(copies, extent)
    for c in range(copies):
        for node in nodes:
            levels, _, _ = place_levels(node, offsets[c])
            yield levels[0]


def write_scene_ply(path, kind: str = "plant", copies: int = 1, size: float = 1.0, seed: int = 1, progress=None) -> dict:
    """Write scene ``kind`` (level 0 of every node, copies on a grid) as one binary PLY with
    vertex colours. Returns {"vertices", "triangles", "bytes"}."""
    prog = progress or (lambda *a: None)
    nv = nt = 0
    for m in _walk(kind, copies, size, seed):  # counts first: the header needs them
        nv, nt = nv + m.vertex_count, nt + m.triangle_count
    head = (f"ply\nformat binary_little_endian 1.0\ncomment massview generate {kind} copies={copies} size={size} seed={seed}\n"
            f"element vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            f"element face {nt}\nproperty list uchar int vertex_indices\nend_header\n")
    path = Path(path)
    with open(path, "wb") as f:
        f.write(head.encode("ascii"))
        for m in _walk(kind, copies, size, seed):
            v = np.empty(m.vertex_count, _VERTEX)
            v["x"], v["y"], v["z"] = m.positions.T
            v["red"], v["green"], v["blue"] = m.colors[:, :3].T
            f.write(v.tobytes())
            prog("vertices", m.vertex_count, nv)
        base = 0
        for m in _walk(kind, copies, size, seed):
            fc = np.empty(m.triangle_count, _FACE)
            fc["n"] = 3
            fc["i"] = m.indices.astype(np.int64) + base
            f.write(fc.tobytes())
            base += m.vertex_count
            prog("faces", m.triangle_count, nt)
    return {"vertices": nv, "triangles": nt, "bytes": path.stat().st_size}
