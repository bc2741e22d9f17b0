"""Binary PLY read in bounded memory: header, vertex blocks, face chunks, corner gathering.

Supports ``binary_little_endian`` / ``binary_big_endian`` files whose first element is
``vertex`` (x, y, z float/double; optional nx, ny, nz; red, green, blue[, alpha] uchar; other
scalar properties skipped) and whose second is ``face`` with one list property of triangles
(``property list uchar|ushort|int|uint int|uint vertex_indices``). Every face record then has a
fixed size, so faces are read with ``np.fromfile`` at computed offsets, a chunk at a time.

A chunk's corners are gathered from the vertex section block by block (``vertex_block``
vertices per read, only the blocks the chunk refers to), so peak memory is one face chunk
plus one vertex block, whatever the file size. Positions are read as float64 (a float or
double PLY alike), so georeferenced coordinates keep their precision until each object is
expressed in its own frame (:mod:`.ingest`). A layout read with ``turn`` (a y-up file) gives
positions and normals turned to z-up, (x, y, z) -> (x, -z, y), wherever vertices are read.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...core.errors import IngestError
from .soup import Corners

__all__ = ["PlyLayout", "read_ply_layout", "vertex_blocks", "face_chunks", "gather_corners", "turn_y_up"]

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
          "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
          "double": "f8", "float64": "f8"}


@dataclass(frozen=True)
class PlyLayout:
    path: Path
    header_bytes: int
    n_vertices: int
    vertex_dtype: np.dtype
    n_faces: int
    face_dtype: np.dtype  # count + 3 indices
    has_colors: bool
    has_normals: bool
    turn: bool = False  # y-up file: vertices are turned to z-up as they are read

    @property
    def faces_offset(self) -> int:
        return self.header_bytes + self.n_vertices * self.vertex_dtype.itemsize

    @property
    def expected_bytes(self) -> int:
        return self.faces_offset + self.n_faces * self.face_dtype.itemsize


def _header(path: Path) -> tuple[list[str], int]:
    with open(path, "rb") as f:
        head = f.read(65536)
    if not head.startswith(b"ply"):
        raise IngestError(f"{path}: not a PLY file (it does not start with 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise IngestError(f"{path}: PLY header has no end_header line in its first 64 KiB (truncated or not PLY)")
    nl = head.find(b"\n", end)
    if nl < 0:
        raise IngestError(f"{path}: PLY header is truncated after end_header")
    return head[:end].decode("ascii", "replace").splitlines(), nl + 1


def read_ply_layout(path, turn: bool = False) -> PlyLayout | None:
    """The layout of a binary triangle PLY, or None when the file is PLY but not of the
    streamable kind (ASCII, other elements first, polygon lists of other types). ``turn``:
    the file is y-up, its vertices are read turned to z-up."""
    path = Path(path)
    lines, hbytes = _header(path)
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format")), None)
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        return None
    end = "<" if fmt == "binary_little_endian" else ">"
    elems: list[tuple[str, int, list]] = []
    for ln in lines:
        w = ln.split()
        if not w or w[0] in ("comment", "obj_info"):
            continue
        if w[0] == "element":
            elems.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elems:
            elems[-1][2].append(w[1:])
    if len(elems) < 2 or elems[0][0] != "vertex" or elems[1][0] != "face":
        return None
    vprops = elems[0][2]
    if any(p[0] == "list" for p in vprops) or any(p[0] not in _TYPES for p in vprops):
        return None
    vdt = np.dtype([(p[1], end + _TYPES[p[0]]) for p in vprops])
    names = set(vdt.names)
    if not {"x", "y", "z"} <= names:
        raise IngestError(f"{path}: PLY vertices have no x, y, z properties")
    fprops = elems[1][2]
    if len(fprops) != 1 or fprops[0][0] != "list" or fprops[0][1] not in _TYPES or fprops[0][2] not in _TYPES:
        return None
    fdt = np.dtype([("n", end + _TYPES[fprops[0][1]]), ("i", end + _TYPES[fprops[0][2]], (3,))])
    lay = PlyLayout(path, hbytes, elems[0][1], vdt, elems[1][1], fdt, {"red", "green", "blue"} <= names, {"nx", "ny", "nz"} <= names,
                    turn)
    size = path.stat().st_size
    if size < lay.expected_bytes:
        raise IngestError(f"{path}: PLY is truncated or has non-triangle faces: its header promises {lay.n_vertices} vertices and "
                          f"{lay.n_faces} triangles ({lay.expected_bytes} bytes) but the file has {size} bytes; re-export or re-download it")
    return lay


def vertex_blocks(lay: PlyLayout, block: int):
    """Yields (first vertex index, structured vertex records) of ``block`` vertices at a time."""
    with open(lay.path, "rb") as f:
        for s in range(0, lay.n_vertices, block):
            f.seek(lay.header_bytes + s * lay.vertex_dtype.itemsize)
            yield s, np.fromfile(f, lay.vertex_dtype, min(block, lay.n_vertices - s))


def face_chunks(lay: PlyLayout, chunk: int):
    """Yields (first face index, triangles (m,3) i8), checking counts and index range."""
    with open(lay.path, "rb") as f:
        for s in range(0, lay.n_faces, chunk):
            f.seek(lay.faces_offset + s * lay.face_dtype.itemsize)
            rec = np.fromfile(f, lay.face_dtype, min(chunk, lay.n_faces - s))
            bad = np.nonzero(rec["n"] != 3)[0]
            if len(bad):
                raise IngestError(f"{lay.path}: face {s + int(bad[0])} has {int(rec['n'][bad[0]])} vertices; the streamed PLY "
                                  "ingest takes triangles only — triangulate the file first")
            tri = rec["i"].astype(np.int64)
            out = np.nonzero((tri < 0) | (tri >= lay.n_vertices))[0]
            if len(out):
                raise IngestError(f"{lay.path}: face {s + int(out[0])} refers to vertex {int(tri[out[0]].max())} but the file has "
                                  f"{lay.n_vertices} vertices; the file is damaged")
            yield s, tri


def turn_y_up(p: np.ndarray | None) -> np.ndarray | None:
    """Positions or normals (...,3) turned from y-up to z-up: (x, y, z) -> (x, -z, y)."""
    if p is None:
        return None
    out = np.empty_like(p)
    out[..., 0], out[..., 1], out[..., 2] = p[..., 0], -p[..., 2], p[..., 1]
    return out


def _fields(rec: np.ndarray, lay: PlyLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Positions f8, colours u8 and normals f32 (or None) of vertex records, turned to z-up
    when the layout says the file is y-up."""
    p = np.stack([rec["x"], rec["y"], rec["z"]], 1).astype(np.float64)
    if lay.has_colors:
        a = rec["alpha"] if "alpha" in rec.dtype.names else np.full(len(rec), 255)
        c = np.stack([rec["red"], rec["green"], rec["blue"], a], 1).astype(np.uint8)
    else:
        c = np.full((len(rec), 4), (200, 200, 200, 255), np.uint8)
    n = np.stack([rec["nx"], rec["ny"], rec["nz"]], 1).astype(np.float32) if lay.has_normals else None
    return (turn_y_up(p), c, turn_y_up(n)) if lay.turn else (p, c, n)


def gather_corners(lay: PlyLayout, tri: np.ndarray, block: int) -> Corners:
    """Corner attributes of triangles ``tri`` (m,3), read from the vertex section one block
    of ``block`` vertices at a time (only the blocks ``tri`` refers to)."""
    m = len(tri)
    pos = np.empty((m * 3, 3), np.float64)
    col = np.empty((m * 3, 4), np.uint8)
    nrm = np.empty((m * 3, 3), np.float32) if lay.has_normals else None
    flat = tri.ravel()
    blk = flat // block
    order = np.argsort(blk, kind="stable")
    cuts = np.nonzero(np.diff(blk[order]))[0] + 1
    with open(lay.path, "rb") as f:
        for sel in np.split(order, cuts):
            if len(sel) == 0:
                continue
            b = int(blk[sel[0]])
            s = b * block
            f.seek(lay.header_bytes + s * lay.vertex_dtype.itemsize)
            rec = np.fromfile(f, lay.vertex_dtype, min(block, lay.n_vertices - s))
            p, c, n = _fields(rec[flat[sel] - s], lay)
            pos[sel], col[sel] = p, c
            if nrm is not None:
                nrm[sel] = n
    if not np.isfinite(pos).all():
        k = int(np.nonzero(~np.isfinite(pos).all(axis=1))[0][0])
        raise IngestError(f"{lay.path}: vertex {int(flat[k])} has a NaN or infinite coordinate; fix or remove it")
    return Corners(pos.reshape(m, 3, 3), col.reshape(m, 3, 4), None if nrm is None else nrm.reshape(m, 3, 3))
