"""One object's mesh at one LOD level, and its byte record in the scene store.

A :class:`Mesh` is what the renderer uploads: positions float32 (v, 3) in the object's LOCAL
frame (world frame unless the object is an instance with a transform), unit normals float32
(v, 3), unlit colours RGBA8 (v, 4) and triangles uint32 (t, 3).

Record layout (little endian, every section padded to 4 bytes; v, t come from the tables)::

    level 0      positions float32 (v, 3)          — the original coordinates, exactly
    level >= 1   positions uint16 (v, 3)           — quantized to the geometry's box [qlo, qhi]
                 normals   int16 (v, 2)            — octahedral encoding (Cigolle et al. 2014)
                 colours   uint8 (v, 4)
                 indices   uint16 (t, 3) if v <= 65536 else uint32 (t, 3)

Quantization adds at most half a step per axis (``quantization_error``) to a level's error.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

__all__ = ["Mesh", "encode_record", "decode_record", "record_size", "quantization_error", "vertex_normals", "crc32"]


@dataclass(frozen=True)
class Mesh:
    """positions f32 (v,3) local coords; normals f32 (v,3) unit; colors u8 (v,4) unlit; indices u32 (t,3)."""

    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    indices: np.ndarray

    @property
    def vertex_count(self) -> int:
        return len(self.positions)

    @property
    def triangle_count(self) -> int:
        return len(self.indices)

    @property
    def nbytes(self) -> int:
        """Decoded bytes (what a GL buffer of this mesh holds)."""
        return decoded_bytes(self.vertex_count, self.triangle_count)


def decoded_bytes(v, t):
    """Decoded size in bytes of v vertices and t triangles (works on arrays)."""
    return v * (12 + 12 + 4) + t * 12


def _pad4(n: int) -> int:
    return (n + 3) & ~3


def record_size(v: int, t: int, level: int) -> int:
    """Bytes of the encoded record of a level with v vertices and t triangles."""
    pos = v * 12 if level == 0 else _pad4(v * 6)
    idx = _pad4(t * 3 * (2 if v <= 65536 else 4))
    return pos + v * 4 + v * 4 + idx


def quantization_error(qlo: np.ndarray, qhi: np.ndarray) -> float:
    """Largest distance a 16-bit quantized position moves (half a step on each axis)."""
    step = (np.asarray(qhi, np.float64) - np.asarray(qlo, np.float64)) / 65535.0
    return float(np.linalg.norm(step / 2))


def _oct_encode(n: np.ndarray) -> np.ndarray:
    n = n.astype(np.float64)
    n = n / np.maximum(np.abs(n).sum(axis=1, keepdims=True), 1e-30)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    neg = z < 0
    ox = np.where(neg, (1 - np.abs(y)) * np.where(x >= 0, 1, -1), x)
    oy = np.where(neg, (1 - np.abs(x)) * np.where(y >= 0, 1, -1), y)
    return np.round(np.clip(np.stack([ox, oy], 1), -1, 1) * 32767).astype(np.int16)


def _oct_decode(e: np.ndarray) -> np.ndarray:
    f = e.astype(np.float32) / 32767.0
    x, y = f[:, 0], f[:, 1]
    z = 1 - np.abs(x) - np.abs(y)
    t = np.clip(-z, 0, None)
    x = x + np.where(x >= 0, -t, t)
    y = y + np.where(y >= 0, -t, t)
    n = np.stack([x, y, z], 1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _quantize(p: np.ndarray, qlo: np.ndarray, qhi: np.ndarray) -> np.ndarray:
    ext = np.where(qhi > qlo, qhi - qlo, 1.0)
    return np.round(np.clip((p.astype(np.float64) - qlo) / ext, 0, 1) * 65535).astype(np.uint16)


def _dequantize(q: np.ndarray, qlo: np.ndarray, qhi: np.ndarray) -> np.ndarray:
    ext = np.where(qhi > qlo, qhi - qlo, 1.0)
    return (qlo + q.astype(np.float64) / 65535.0 * ext).astype(np.float32)


def encode_record(mesh: Mesh, level: int, qlo: np.ndarray, qhi: np.ndarray) -> bytes:
    """The record of ``mesh`` at ``level`` (see the module docstring)."""
    v, t = mesh.vertex_count, mesh.triangle_count
    parts = []
    if level == 0:
        parts.append(np.ascontiguousarray(mesh.positions, "<f4").tobytes())
    else:
        parts.append(_quantize(mesh.positions, qlo, qhi).astype("<u2").tobytes().ljust(_pad4(v * 6), b"\0"))
    parts.append(_oct_encode(mesh.normals).astype("<i2").tobytes())
    parts.append(np.ascontiguousarray(mesh.colors, np.uint8).tobytes())
    idt = "<u2" if v <= 65536 else "<u4"
    parts.append(mesh.indices.astype(idt).tobytes().ljust(_pad4(t * 3 * np.dtype(idt).itemsize), b"\0"))
    return b"".join(parts)


def decode_record(buf, v: int, t: int, level: int, qlo: np.ndarray, qhi: np.ndarray) -> Mesh:
    """Inverse of :func:`encode_record`; raises ValueError when ``buf`` is too short."""
    buf = memoryview(buf)
    if len(buf) < record_size(v, t, level):
        raise ValueError(f"record holds {len(buf)} bytes, {record_size(v, t, level)} expected")
    o = 0
    if level == 0:
        pos = np.frombuffer(buf, "<f4", v * 3, o).reshape(v, 3).astype(np.float32)
        o += v * 12
    else:
        pos = _dequantize(np.frombuffer(buf, "<u2", v * 3, o).reshape(v, 3), qlo, qhi)
        o += _pad4(v * 6)
    nrm = _oct_decode(np.frombuffer(buf, "<i2", v * 2, o).reshape(v, 2)).astype(np.float32)
    o += v * 4
    col = np.frombuffer(buf, np.uint8, v * 4, o).reshape(v, 4).copy()
    o += v * 4
    idt = "<u2" if v <= 65536 else "<u4"
    idx = np.frombuffer(buf, idt, t * 3, o).reshape(t, 3).astype(np.uint32)
    return Mesh(pos, nrm, col, idx)


def vertex_normals(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals float32 (v, 3); (0, 0, 1) where undefined."""
    p = p.astype(np.float64)
    fn = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
    idx = tri.ravel()
    w = np.repeat(fn, 3, axis=0)
    n = np.stack([np.bincount(idx, w[:, c], len(p)) for c in range(3)], 1)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    out = np.where(ln > 1e-30, n / np.maximum(ln, 1e-30), [0.0, 0.0, 1.0])
    return out.astype(np.float32)


def crc32(buf) -> int:
    return zlib.crc32(buf) & 0xFFFFFFFF
