"""Mesh inputs for ``prepare scene``: PLY, OBJ, STL, OFF, glTF/GLB, read into corners.

An input is either *structured* — objects from the file's own structure (glTF nodes with
their world transforms, OBJ ``o``/``g`` groups) — or one unstructured *soup* (PLY, STL, OFF,
an OBJ without groups, a glTF with one mesh node) that :mod:`.soup` splits into objects. A
binary triangle PLY is read with :mod:`.plystream` (streamed when it is large, whole when it
is small: the same reader either way); an OBJ with :func:`read_obj`, in file order (trimesh
only for its colours, when it has vertex colours or materials); everything else goes through
trimesh. Positions are float64 throughout (georeferenced coordinates keep their precision;
:mod:`.ingest` expresses each object in float32 relative to its own origin).

Colours are the file's vertex or face colours, or its materials' (per OBJ material: each is
read as its own mesh): a plain colour (``Kd``, ``baseColorFactor``), or a texture (``map_Kd``,
``baseColorTexture``) baked into the vertex colours by :mod:`.texture` — a scene store keeps no
textures, and ``open_input`` warns, naming the file and how many materials or meshes were baked.

Normals are the file's where it has them: PLY ``nx ny nz``, OBJ ``vn`` (per corner, indexed
apart from the positions), glTF ``NORMAL``; a glTF node's transform turns them by its inverse
transpose. An OBJ corner without a ``vn`` gets a NaN normal: :mod:`.ingest` computes the
normals of any object with such a corner (or a zero one) and says so.

massview's world is +z up. glTF/GLB is +y up by its specification (what Blender, Sketchfab and
trimesh write); OBJ, PLY, STL and OFF have no convention. :func:`up_axis` picks the file's up
axis (``auto``: y for glTF/GLB, z for the rest; ``y`` or ``z`` for every input) and a y-up input
is turned to z-up as it is read, by :data:`Y_TO_Z` (+90° about x: (x, y, z) -> (x, -z, y), a
proper rotation, so handedness and winding are kept): positions and normals alike, on every
path (a glTF node's world transform is preceded by it, an OBJ group's identity becomes it, a
soup's and a binary PLY's vertices — streamed or not — are turned where they are read).

Inputs are checked before anything is written: a directory, an unknown suffix, a file trimesh
cannot parse, an empty mesh, NaN/infinite coordinates or face indices out of range raise
:class:`IngestError` naming the file (and, for an OBJ, the line).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...core.errors import IngestError
from .plystream import PlyLayout, face_chunks, gather_corners, read_ply_layout, turn_y_up, vertex_blocks
from .soup import Corners
from .texture import GREY, is_textured, trimesh_colors

__all__ = ["SUFFIXES", "UP_CHOICES", "Y_TO_Z", "up_axis", "check_input", "StructuredObject", "MemorySoup", "ObjFile", "open_input", "read_obj", "transform_normals"]

SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")
UP_CHOICES = ("auto", "y", "z")
Y_TO_Z = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])  # (x, y, z) -> (x, -z, y)


def up_axis(path: Path, up: str) -> str:
    """The up axis ("y" or "z") of input ``path`` under the ``--up`` choice ``up``."""
    if up == "auto":
        return "y" if Path(path).suffix.lower() in (".gltf", ".glb") else "z"
    return up


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
    if p.is_file() and p.stat().st_size == 0:
        raise IngestError(f"{p}: the file is empty (0 bytes); nothing to ingest")
    return p


def _validate(path: Path, p: np.ndarray, f: np.ndarray, what: str = "") -> None:
    if len(f) == 0 or len(p) == 0:
        raise IngestError(f"{path}{what}: the mesh is empty (no triangles); nothing to ingest")
    bad = np.nonzero(~np.isfinite(p).all(axis=1))[0]
    if len(bad):
        raise IngestError(f"{path}{what}: {len(bad)} vertices have NaN or infinite coordinates (first: vertex {int(bad[0])}); fix or remove them")
    if f.min() < 0 or f.max() >= len(p):
        raise IngestError(f"{path}{what}: a face refers to vertex {int(f.max())} but there are {len(p)} vertices; the file is damaged")


def file_normals(m) -> np.ndarray | None:
    """The vertex normals (v,3) f8 a trimesh mesh was loaded with (glTF ``NORMAL``, PLY
    nx/ny/nz), or None when the file brought none. (trimesh computes ``vertex_normals`` on
    demand; normals from the file are the ones already in its cache, which is also how
    trimesh's own exporters tell them apart.)"""
    n = m._cache.cache.get("vertex_normals")
    if n is None or np.shape(n) != np.shape(m.vertices):
        return None
    return np.asarray(n, np.float64)


def _corners_of(m, path: Path, what: str) -> Corners:
    p = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64).reshape(-1, 3)
    _validate(path, p, f, what)
    col = trimesh_colors(m)
    n = file_normals(m)
    return Corners(p[f], col if col.ndim == 3 else col[f], None if n is None else n[f].astype(np.float32))


def transform_normals(n: np.ndarray | None, xf: np.ndarray) -> np.ndarray | None:
    """Normals (...,3) through the 4x4 ``xf`` (its linear part's inverse transpose), float32,
    not normalised (:mod:`.ingest` normalises); None stays None, as does a singular ``xf``."""
    if n is None:
        return None
    try:
        inv = np.linalg.inv(np.asarray(xf, np.float64)[:3, :3])
    except np.linalg.LinAlgError:
        return None
    return (np.asarray(n, np.float64) @ inv).astype(np.float32)


@dataclass(frozen=True)
class ObjFile:
    """An OBJ read in file order: corner positions f8 (t,3,3) and normals f32 (t,3,3) (NaN
    where a corner names no ``vn``; None when no corner does) of every triangle, faces of more
    than 3 corners fanned from their first corner; ``labels`` (t,) i8 the ``o``/``g`` group of
    each triangle; ``colored``: the file has vertex colours or materials (read by trimesh)."""

    positions: np.ndarray
    normals: np.ndarray | None
    labels: np.ndarray
    groups: int
    colored: bool
    mtllibs: tuple = ()  # the material libraries the file names (``mtllib``)
    uses_materials: bool = False  # it has ``usemtl`` lines
    vertex_colors: bool = False  # some ``v`` line has r g b


def _obj_index(tok: str, n: int, what: str, path: Path, lineno: int) -> int:
    """0-based index of a 1-based (or negative: relative to the ``n`` defined so far) OBJ index."""
    try:
        i = int(tok)
    except ValueError:
        raise IngestError(f"{path}:{lineno}: face corner has {what} index {tok!r}, not an integer; the file is damaged") from None
    k = i - 1 if i > 0 else n + i
    if i == 0 or not 0 <= k < n:
        plural = {"vertex": "vertices"}.get(what, f"{what}s")
        raise IngestError(f"{path}:{lineno}: face refers to {what} {i} but only {n} {plural if n != 1 else what} "
                          f"{'are' if n != 1 else 'is'} defined before it; "
                          "the file is damaged")
    return k


def read_obj(path: Path) -> ObjFile:
    """The triangles of an OBJ (``v``, ``vn``, ``f v``, ``f v/vt``, ``f v//vn``, ``f v/vt/vn``;
    negative indices count back from the last defined), checked line by line: a malformed
    coordinate or index raises :class:`IngestError` naming the file and line."""
    v: list = []
    vn: list = []
    tv: list = []  # corner vertex indices, 3 per triangle
    tn: list = []  # corner normal indices (-1: none)
    labels: list = []
    group, seen, colored = 0, {}, False
    mtllibs: list = []
    usemtl = vcol = False
    with open(path, "r", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            w = line.split()
            if not w:
                continue
            key = w[0]
            if key in ("v", "vn"):
                try:
                    xyz = (float(w[1]), float(w[2]), float(w[3]))
                except (ValueError, IndexError):
                    raise IngestError(f"{path}:{lineno}: {key!r} line needs three numbers, got {' '.join(w[1:4])!r}; "
                                      "the file is damaged") from None
                (v if key == "v" else vn).append(xyz)
                vcol |= key == "v" and len(w) >= 7
                colored |= vcol
            elif key in ("o", "g"):
                group = seen.setdefault(" ".join(w[1:]) or f"_{lineno}", len(seen))
            elif key == "usemtl":
                colored = usemtl = True
            elif key == "mtllib":
                mtllibs += line.split(None, 1)[1:2]
            elif key == "f":
                if len(w) < 4:
                    raise IngestError(f"{path}:{lineno}: face has {len(w) - 1} corners; a face needs at least 3")
                cv, cn = [], []
                for tok in w[1:]:
                    parts = tok.split("/")
                    cv.append(_obj_index(parts[0], len(v), "vertex", path, lineno))
                    cn.append(_obj_index(parts[2], len(vn), "normal", path, lineno) if len(parts) > 2 and parts[2] else -1)
                for j in range(1, len(cv) - 1):  # fan from the first corner
                    tv += (cv[0], cv[j], cv[j + 1])
                    tn += (cn[0], cn[j], cn[j + 1])
                labels += [group] * (len(cv) - 2)
    pos = np.asarray(v, np.float64).reshape(-1, 3)
    tri = np.asarray(tv, np.int64).reshape(-1, 3)
    _validate(path, pos, tri)
    nidx = np.asarray(tn, np.int64).reshape(-1, 3)
    nrm = None
    if (nidx >= 0).any():
        table = np.concatenate([np.asarray(vn, np.float32).reshape(-1, 3), np.full((1, 3), np.nan, np.float32)])
        nrm = table[nidx]  # -1: the NaN row
    return ObjFile(pos[tri], nrm, np.asarray(labels, np.int64), max(len(seen), 1), colored, tuple(mtllibs), usemtl, vcol)


def _canonical_order(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation (t,3): each triangle's corners starting at its smallest corner position, winding
    kept; order (t,): triangles sorted by their rotated corners) of corners (t,3,3)."""
    flat = c.reshape(-1, 3)
    rank = np.empty(len(flat), np.int64)
    rank[np.lexsort(flat.T[::-1])] = np.arange(len(flat))
    rot = (rank.reshape(-1, 3).argmin(axis=1)[:, None] + np.arange(3)) % 3
    cc = np.take_along_axis(c, rot[:, :, None], 1).reshape(-1, 9)
    return rot, np.lexsort(cc.T[::-1])


def _obj_parts(path: Path) -> list:
    """The OBJ as trimesh reads it, one mesh per material, each with its own material (forced
    into one mesh, trimesh packs the materials into one atlas, and a plain ``Kd`` material
    beside a textured one came out transparent black)."""
    import trimesh

    loaded = _load_trimesh(path, one_mesh=False)
    if not isinstance(loaded, trimesh.Scene):
        return [loaded]
    parts = []
    for node in sorted(loaded.graph.nodes_geometry):
        xf, gname = loaded.graph[node]
        geom = loaded.geometry[gname]
        if hasattr(geom, "faces"):
            if not np.array_equal(xf, np.eye(4)):  # (an OBJ's parts are not moved; should one be: as trimesh places it)
                geom = geom.copy()
                geom.apply_transform(xf)
            parts.append(geom)
    return parts


def _obj_colors(path: Path, obj: ObjFile, warn: list, materials_missing: bool = False,
                textured: list | None = None) -> np.ndarray:
    """Corner colours u8 (t,3,4) of an OBJ's triangles: grey, or (vertex colours, materials)
    what trimesh makes of them — a texture baked per vertex (:func:`.texture.trimesh_colors`;
    the name of each textured material is appended to ``textured``) — matched to the file's
    triangles by their corner positions (trimesh regroups faces by material and splits quads
    its own way)."""
    grey = np.empty((len(obj.positions), 3, 4), np.uint8)
    grey[:] = GREY
    if not obj.colored or (materials_missing and not obj.vertex_colors):
        return grey
    tcs, cols = [], []
    for m in _obj_parts(path):
        f = np.asarray(m.faces, np.int64).reshape(-1, 3)
        col = trimesh_colors(m)
        tcs.append(np.asarray(m.vertices, np.float64)[f])
        cols.append(col if col.ndim == 3 else col[f])
        if textured is not None and is_textured(m):
            textured.append(getattr(getattr(m.visual, "material", None), "name", None) or f"material {len(textured) + 1}")
    tc, col = np.concatenate(tcs), np.concatenate(cols)
    if tc.shape != obj.positions.shape:
        warn.append(f"{path}: trimesh reads {len(tc)} triangles where massview reads {len(obj.positions)}; its colours "
                    "are not used (grey)")
        return grey
    rot_t, ord_t = _canonical_order(tc)
    rot_m, ord_m = _canonical_order(obj.positions)
    if not np.array_equal(np.take_along_axis(tc, rot_t[:, :, None], 1)[ord_t],
                          np.take_along_axis(obj.positions, rot_m[:, :, None], 1)[ord_m]):
        warn.append(f"{path}: trimesh's triangles differ from the file's; its colours are not used (grey)")
        return grey
    out = np.empty_like(col)
    out[ord_m[:, None], rot_m[ord_m]] = np.take_along_axis(col[ord_t], rot_t[ord_t][:, :, None], 1)
    return out


def _load_trimesh(path: Path, one_mesh: bool = True):
    """The file as trimesh reads it: a glTF/GLB as a scene, anything else as one mesh (as a
    scene of one mesh per material with ``one_mesh=False``, where trimesh makes one)."""
    import trimesh

    try:
        if path.suffix.lower() in (".gltf", ".glb"):
            return trimesh.load_scene(str(path))
        return trimesh.load(str(path), process=False, **({"force": "mesh"} if one_mesh else {}))
    except IngestError:
        raise
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds on bad files
        raise IngestError(f"{path}: cannot be read as {path.suffix[1:].upper()} ({type(e).__name__}: {e}); check the file") from None


def _scene_objects(path: Path, scene, turn: bool, textured: list | None = None) -> list[StructuredObject] | MemorySoup:
    """The mesh nodes of a glTF/GLB scene as objects (one alone as a soup); the name of each
    textured mesh is appended to ``textured`` (once, however many nodes place it)."""
    nodes = list(scene.graph.nodes_geometry)
    if not nodes:
        raise IngestError(f"{path}: the scene has no mesh nodes; nothing to ingest")
    out = []
    for node in sorted(nodes):
        xf, gname = scene.graph[node]
        geom = scene.geometry[gname]
        if not hasattr(geom, "faces"):
            continue  # point clouds and paths carry no triangles
        xf = (Y_TO_Z @ np.asarray(xf, np.float64)) if turn else np.asarray(xf, np.float64)
        if textured is not None and str(gname) not in textured and is_textured(geom):
            textured.append(str(gname))
        out.append(StructuredObject(str(node), _corners_of(geom, path, f" (node {node})"), xf, str(gname)))
    if not out:
        raise IngestError(f"{path}: the scene has no triangle meshes; nothing to ingest")
    if len(out) == 1:
        c, xf = out[0].corners, out[0].transform
        p = np.einsum("ij,tkj->tki", xf[:3, :3], c.positions) + xf[:3, 3]
        t = np.arange(c.count * 3).reshape(-1, 3)
        n = transform_normals(c.normals, xf)
        return MemorySoup(path, p.reshape(-1, 3), c.colors, None if n is None else n.reshape(-1, 3), t)
    return out


def _missing_materials(path: Path, obj: ObjFile) -> str | None:
    """A warning when the OBJ's materials cannot be found (its ``mtllib`` files are missing
    next to it, or it uses materials but names no library): trimesh then draws them grey."""
    if not obj.uses_materials:
        return None
    def found(rest: str) -> bool:  # one name with spaces, or several names
        return (path.parent / rest.strip()).is_file() or any((path.parent / t).is_file() for t in rest.split())

    missing = [m.strip() for m in obj.mtllibs if not found(m)]
    if not obj.mtllibs:
        return f"{path}: uses materials (usemtl) but names no material library (mtllib); drawn grey"
    if len(missing) == len(obj.mtllibs):
        return (f"{path}: material library {', '.join(missing)} not found next to it; drawn grey "
                "(put the .mtl beside the OBJ for its colours)")
    return None


def _obj_input(path: Path, warn: list, turn: bool, textured: list) -> list[StructuredObject] | MemorySoup:
    obj = read_obj(path)
    msg = _missing_materials(path, obj)
    if msg:
        warn.append(msg)
    col = _obj_colors(path, obj, warn, msg is not None, textured)
    n, lab = obj.normals, obj.labels
    if obj.groups > 1 and len(np.unique(lab)) > 1:
        xf = Y_TO_Z if turn else np.eye(4)
        return [StructuredObject(f"group {g}", Corners(obj.positions[lab == g], col[lab == g], None if n is None else n[lab == g]),
                                 xf.copy(), f"group {g}") for g in np.unique(lab)]
    t = len(obj.positions)
    p, n = obj.positions.reshape(-1, 3), None if n is None else n.reshape(-1, 3)
    if turn:
        p, n = turn_y_up(p), turn_y_up(n)
    return MemorySoup(path, p, col, n, np.arange(t * 3).reshape(-1, 3))


def open_input(path: Path, stream_bytes: int, warn: list | None = None, up: str = "auto",
               textures: dict | None = None) -> list[StructuredObject] | MemorySoup | PlyLayout:
    """Structured objects, a soup in RAM, or (a binary triangle PLY of at least
    ``stream_bytes`` bytes) its layout for the streamed ingest. Normals come from the file
    where it has them (PLY nx/ny/nz, OBJ ``vn`` per corner — NaN for corners without one —,
    glTF ``NORMAL``), through any node transform. ``up`` (:data:`UP_CHOICES`): the file's up
    axis, see :func:`up_axis`; a y-up file comes back turned to z-up. ``warn`` collects
    messages for the user; ``textures`` gets ``str(path)`` -> the number of textured materials
    (OBJ) or meshes (glTF, others) whose texture was baked to per-vertex colours, if any."""
    warn = [] if warn is None else warn
    path = check_input(path)
    if up not in UP_CHOICES:
        raise IngestError(f"--up must be one of {', '.join(UP_CHOICES)}, got {up!r}")
    textured: list[str] = []
    src = _open(path, up_axis(path, up) == "y", stream_bytes, warn, textured)
    if textured:
        what = ("material", "materials") if path.suffix.lower() == ".obj" else ("mesh", "meshes")
        what = what[len(textured) > 1]
        names = ", ".join(textured[:3]) + (", ..." if len(textured) > 3 else "")
        warn.append(f"{path}: {len(textured)} textured {what} ({names}) baked to per-vertex colours (a scene store keeps no "
                    "textures; each vertex gets the texture's mean over its faces): detail finer than the mesh's vertices is lost")
        if textures is not None:
            textures[str(path)] = len(textured)
    return src


def _open(path: Path, turn: bool, stream_bytes: int, warn: list, textured: list):
    suf = path.suffix.lower()
    if suf == ".ply":
        lay = read_ply_layout(path, turn)
        if lay is not None:
            if lay.n_faces == 0 or lay.n_vertices == 0:
                raise IngestError(f"{path}: the mesh is empty (no triangles); nothing to ingest")
            return lay if path.stat().st_size >= stream_bytes else _read_whole_ply(lay)
    if suf == ".obj":
        return _obj_input(path, warn, turn, textured)
    if suf in (".gltf", ".glb"):
        return _scene_objects(path, _load_trimesh(path), turn, textured)
    m = _load_trimesh(path)
    p = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64).reshape(-1, 3)
    _validate(path, p, f)
    n = file_normals(m)
    n = None if n is None else n.astype(np.float32)
    if turn:
        p, n = turn_y_up(p), turn_y_up(n)
    if is_textured(m):
        textured.append(path.name)
    return MemorySoup(path, p, trimesh_colors(m), n, f)


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
