"""Mesh inputs for ``prepare scene``: PLY, OBJ, STL, OFF, glTF/GLB, read into corners.

An input is either *structured* — objects from the file's own structure (glTF nodes with
their world transforms, OBJ ``o``/``g`` groups) — or one unstructured *soup* (PLY, STL, OFF,
an OBJ without groups, a glTF with one mesh node) that :mod:`.soup` splits into objects. A
binary triangle PLY is read with :mod:`.plystream` (streamed when it is large, whole when it
is small: the same reader either way); everything else goes through trimesh. Positions are
float64 throughout (georeferenced coordinates keep their precision; :mod:`.ingest` expresses
each object in float32 relative to its own origin). Inputs are checked before anything is
written: a directory, an unknown suffix, a file trimesh cannot parse, an empty mesh,
NaN/infinite coordinates or face indices out of range raise :class:`IngestError` naming the
file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...core.errors import IngestError
from .plystream import PlyLayout, face_chunks, gather_corners, read_ply_layout, vertex_blocks
from .soup import Corners

__all__ = ["SUFFIXES", "check_input", "StructuredObject", "MemorySoup", "open_input"]

SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")
_GREY = (200, 200, 200, 255)


@dataclass(frozen=True)
class StructuredObject:
    """One object of a structured input: corners in the geometry's own frame, its local ->
    world transform (4,4) f8, and a key naming its geometry (equal keys: same geometry)."""

    name: str
    corners: Corners
    transform: np.ndarray
    geometry_key: str


@dataclass(frozen=True)
class MemorySoup:
    """A soup held in RAM: positions f8 (v,3), colours u8 (v,4) or corner colours u8 (t,3,4),
    normals f32 (v,3) or None, faces i8 (t,3)."""

    path: Path
    positions: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None
    faces: np.ndarray

    def corners(self, sel: np.ndarray) -> Corners:
        f = self.faces[sel]
        col = self.colors[sel] if self.colors.ndim == 3 else self.colors[f]
        return Corners(self.positions[f], col, None if self.normals is None else self.normals[f])


def check_input(path) -> Path:
    p = Path(path)
    if p.is_dir():
        raise IngestError(f"{p} is a directory; pass the mesh files inside it (e.g. {p}/*.ply)")
    if not p.exists():
        raise IngestError(f"{p}: no such file")
    if p.suffix.lower() not in SUFFIXES:
        raise IngestError(f"{p}: unknown mesh format {p.suffix!r}; massview reads {', '.join(SUFFIXES)}")
    return p


def _validate(path: Path, p: np.ndarray, f: np.ndarray, what: str = "") -> None:
    if len(f) == 0 or len(p) == 0:
        raise IngestError(f"{path}{what}: the mesh is empty (no triangles); nothing to ingest")
    bad = np.nonzero(~np.isfinite(p).all(axis=1))[0]
    if len(bad):
        raise IngestError(f"{path}{what}: {len(bad)} vertices have NaN or infinite coordinates (first: vertex {int(bad[0])}); fix or remove them")
    if f.min() < 0 or f.max() >= len(p):
        raise IngestError(f"{path}{what}: a face refers to vertex {int(f.max())} but there are {len(p)} vertices; the file is damaged")


def _trimesh_colors(m) -> np.ndarray:
    """Vertex colours (v,4) or corner colours (t,3,4) u8 of a trimesh mesh (grey if none)."""
    vis = m.visual
    kind = getattr(vis, "kind", None)
    try:
        if kind == "texture":
            vis = vis.to_color()
            kind = vis.kind
        if kind == "vertex":
            return np.asarray(vis.vertex_colors, np.uint8)[:, :4]
        if kind == "face":
            return np.repeat(np.asarray(vis.face_colors, np.uint8)[:, None, :4], 3, axis=1)
    except Exception:  # noqa: BLE001 - a material trimesh cannot turn into colours: grey
        pass
    return np.tile(np.array(_GREY, np.uint8), (len(m.vertices), 1))


def _corners_of(m, path: Path, what: str) -> Corners:
    p = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64).reshape(-1, 3)
    _validate(path, p, f, what)
    col = _trimesh_colors(m)
    return Corners(p[f], col if col.ndim == 3 else col[f], None)


def _obj_groups(path: Path) -> np.ndarray | None:
    """Per-triangle group label of an OBJ (fan triangulation of each face line), or None
    without groups; checks face indices against the vertices defined so far."""
    labels, group, nv, seen = [], 0, 0, {}
    with open(path, "r", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            w = line.split()
            if not w:
                continue
            if w[0] == "v":
                nv += 1
            elif w[0] in ("o", "g"):
                group = seen.setdefault(" ".join(w[1:]) or f"_{lineno}", len(seen))
            elif w[0] == "f":
                idx = [int(t.split("/")[0]) for t in w[1:]]
                for i in idx:
                    if i == 0 or i > nv or i < -nv:
                        raise IngestError(f"{path}:{lineno}: face refers to vertex {i} but only {nv} vertices are defined before it; "
                                          "the file is damaged")
                labels += [group] * max(len(idx) - 2, 0)
    lab = np.asarray(labels, np.int64)
    return lab if len(seen) > 1 and len(np.unique(lab)) > 1 else None


def _load_trimesh(path: Path):
    import trimesh

    try:
        if path.suffix.lower() in (".gltf", ".glb"):
            return trimesh.load_scene(str(path))
        return trimesh.load(str(path), process=False, force="mesh")
    except IngestError:
        raise
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds on bad files
        raise IngestError(f"{path}: cannot be read as {path.suffix[1:].upper()} ({type(e).__name__}: {e}); check the file") from None


def _scene_objects(path: Path, scene) -> list[StructuredObject] | MemorySoup:
    nodes = list(scene.graph.nodes_geometry)
    if not nodes:
        raise IngestError(f"{path}: the scene has no mesh nodes; nothing to ingest")
    out = []
    for node in sorted(nodes):
        xf, gname = scene.graph[node]
        geom = scene.geometry[gname]
        if not hasattr(geom, "faces"):
            continue  # point clouds and paths carry no triangles
        out.append(StructuredObject(str(node), _corners_of(geom, path, f" (node {node})"), np.asarray(xf, np.float64), str(gname)))
    if not out:
        raise IngestError(f"{path}: the scene has no triangle meshes; nothing to ingest")
    if len(out) == 1:
        c = out[0].corners
        p = np.einsum("ij,tkj->tki", out[0].transform[:3, :3], c.positions) + out[0].transform[:3, 3]
        t = np.arange(c.count * 3).reshape(-1, 3)
        return MemorySoup(path, p.reshape(-1, 3), c.colors, None, t)
    return out


def open_input(path: Path, stream_bytes: int) -> list[StructuredObject] | MemorySoup | PlyLayout:
    """Structured objects, a soup in RAM, or (a binary triangle PLY of at least
    ``stream_bytes`` bytes) its layout for the streamed ingest."""
    path = check_input(path)
    suf = path.suffix.lower()
    if suf == ".ply":
        lay = read_ply_layout(path)
        if lay is not None:
            if lay.n_faces == 0 or lay.n_vertices == 0:
                raise IngestError(f"{path}: the mesh is empty (no triangles); nothing to ingest")
            return lay if path.stat().st_size >= stream_bytes else _read_whole_ply(lay)
    if suf == ".obj":
        labels = _obj_groups(path)
        m = _load_trimesh(path)
        c = _corners_of(m, path, "")
        if labels is not None and len(labels) == c.count:
            return [StructuredObject(f"group {g}", Corners(c.positions[labels == g], c.colors[labels == g], None), np.eye(4), f"group {g}")
                    for g in np.unique(labels)]
        return MemorySoup(path, c.positions.reshape(-1, 3), c.colors, None, np.arange(c.count * 3).reshape(-1, 3))
    if suf in (".gltf", ".glb"):
        return _scene_objects(path, _load_trimesh(path))
    m = _load_trimesh(path)
    p = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64).reshape(-1, 3)
    _validate(path, p, f)
    return MemorySoup(path, p, _trimesh_colors(m), None, f)


def _read_whole_ply(lay: PlyLayout) -> MemorySoup:
    """A binary triangle PLY read whole with the streaming reader's own code."""
    from .plystream import _fields

    rec = np.concatenate([b for _, b in vertex_blocks(lay, 1 << 22)])
    p, c, n = _fields(rec, lay)
    f = np.concatenate([t for _, t in face_chunks(lay, 1 << 22)])
    _validate(lay.path, p, f)
    return MemorySoup(lay.path, p, c, n, f)


def stream_bounds(lay: PlyLayout, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Box of all vertices of a PLY, read block by block; NaN/inf raise IngestError."""
    from .plystream import _fields

    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for s, rec in vertex_blocks(lay, block):
        p = _fields(rec, lay)[0]
        bad = np.nonzero(~np.isfinite(p).all(axis=1))[0]
        if len(bad):
            raise IngestError(f"{lay.path}: vertex {s + int(bad[0])} has a NaN or infinite coordinate; fix or remove it")
        lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
    return lo, hi


def stream_corners(lay: PlyLayout, chunk: int, block: int):
    """Yields (first face, Corners) of ``chunk`` faces at a time."""
    for s, tri in face_chunks(lay, chunk):
        yield s, gather_corners(lay, tri, block)
