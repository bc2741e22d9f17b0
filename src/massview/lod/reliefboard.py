"""Reliefboards as data: the board frame, the grid mesh built from the four maps, the wire codec
(Süß et al. 2010, §5).

A Reliefboard approximates one object seen from one direction. Its **frame** is fixed at
creation: centre ``c`` (the object's box centre), radius ``r`` (half the box diagonal, so the
object lies in the cube ``[-r, r]³`` around ``c``), and the direction ``d`` from the observer to
``c``. The axes follow the camera convention: ``right = normalize(d × z_up)``, ``up = right × d``,
``back = -d`` (towards the observer); board coordinates (x, y, z) are along (right, up, back).

The four **maps** are S×S arrays (S = the board's resolution in pixels, the object's projected
size at request time), rows from the bottom (GL order), pixel (i, j) centred at
``x = -r + (j + ½)·2r/S``, ``y = -r + (i + ½)·2r/S``:

* distance — float32, world units from the front plane ``z = +r`` to the surface, in [0, 2r];
* stencil  — bool, the pixel is covered by the object's projection;
* colour   — uint8 RGB, the unlit vertex colour;
* normal   — float32 unit world-space surface normal.

The **mesh** has one vertex per covered pixel, at ``c + x·right + y·up + (r − distance)·back``
(stored relative to ``c``: the renderer adds ``c`` in float64),
with the pixel's colour and normal; every 2×2 block of pixels gives two triangles when all four
are covered and one when three are, so the mesh is cut where the stencil is empty.

The **wire encoding** (:func:`encode_board`/:func:`decode_board`) sends a fixed header, the
stencil as packed bits, and per covered pixel the distance as uint16 over [0, 2r], the colour
as 3 bytes and the normal octahedron-encoded as 2 int16: 9 bytes per vertex plus S²/8, against
~52 bytes per vertex for float vertices with triangle indices. Triangles are rebuilt from the
stencil on arrival.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError, CorruptBlockError

__all__ = ["BoardFrame", "Reliefboard", "board_frame", "grid_triangles", "encode_board", "decode_board",
           "angle_error_deg"]

_HEADER = struct.Struct("<4sqiid3d3dd")
_MAGIC = b"RB01"


@dataclass(frozen=True)
class BoardFrame:
    """center (3,) float64 world; radius float (world units); direction (3,) unit float64
    observer → centre; size: resolution S in pixels; axes: (3, 3) float64 columns right, up, back."""

    center: tuple
    radius: float
    direction: tuple
    size: int

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, np.float64)
        n = float(np.linalg.norm(d))
        if d.shape != (3,) or not np.isfinite(n) or n == 0:
            raise ConfigError(f"board direction must be a non-zero 3-vector, got {self.direction!r}")
        if not (self.radius > 0 and np.isfinite(self.radius)):
            raise ConfigError(f"board radius must be positive, got {self.radius}")
        if int(self.size) < 2:
            raise ConfigError(f"board resolution must be at least 2 pixels, got {self.size}")
        object.__setattr__(self, "direction", tuple(float(a) for a in d / n))
        object.__setattr__(self, "center", tuple(float(a) for a in self.center))
        object.__setattr__(self, "radius", float(self.radius))
        object.__setattr__(self, "size", int(self.size))

    @property
    def axes(self) -> np.ndarray:
        f = np.asarray(self.direction)
        right = np.cross(f, [0.0, 0.0, 1.0])
        if np.linalg.norm(right) < 1e-9:  # looking straight up or down
            right = np.cross(f, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, f)
        return np.stack([right, up, -f], axis=1)

    def view_matrix(self) -> np.ndarray:
        """4x4 world → board coordinates (float64, column vectors)."""
        a = self.axes
        v = np.eye(4)
        v[:3, :3] = a.T
        v[:3, 3] = -a.T @ np.asarray(self.center)
        return v

    def projection_matrix(self) -> np.ndarray:
        """Orthographic projection of the cube [-r, r]³ (board coordinates) to NDC; the front
        plane z = +r maps to depth -1."""
        r = self.radius
        return np.diag([1.0 / r, 1.0 / r, -1.0 / r, 1.0])

    def pixel_centres(self) -> np.ndarray:
        """(S,) board coordinate of pixel centres along x (columns) and y (rows)."""
        s, r = self.size, self.radius
        return -r + (np.arange(s) + 0.5) * (2 * r / s)


def board_frame(box_lo, box_hi, direction, size: int) -> BoardFrame:
    """The frame of a board for an object with box ``[box_lo, box_hi]`` (a hair larger than
    the half diagonal so no vertex falls on the clip planes)."""
    lo, hi = np.asarray(box_lo, np.float64), np.asarray(box_hi, np.float64)
    r = max(float(np.linalg.norm(hi - lo)) / 2 * 1.001, 1e-6)
    return BoardFrame(tuple((lo + hi) / 2), r, tuple(direction), size)


def grid_triangles(stencil: np.ndarray) -> np.ndarray:
    """uint32 (3T,) indices into the covered pixels (row-major order) of an (S, S) bool stencil:
    two triangles per fully covered 2×2 block, one per block with three covered pixels."""
    s = np.asarray(stencil, bool)
    idx = np.full(s.shape, -1, np.int64)
    idx[s] = np.arange(int(s.sum()))
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    ca, cb, cc, cd = a >= 0, b >= 0, c >= 0, d >= 0
    full = ca & cb & cc & cd
    tris = [np.stack([a, b, d], 1)[full], np.stack([a, d, c], 1)[full]]
    three = (ca.astype(int) + cb + cc + cd) == 3
    for keep, tri in (((~ca) & three, (b, d, c)), ((~cb) & three, (a, d, c)),
                      ((~cc) & three, (a, b, d)), ((~cd) & three, (a, b, c))):
        tris.append(np.stack(tri, 1)[keep])
    return np.concatenate(tris).astype(np.uint32).ravel()


@dataclass(frozen=True)
class Reliefboard:
    """A board of object ``object_id``: its frame, the (S, S) bool stencil, and per covered pixel
    (row-major) the distance (N,) float32, colour (N, 3) uint8 and normal (N, 3) float32."""

    object_id: int
    frame: BoardFrame
    stencil: np.ndarray
    distance: np.ndarray
    color: np.ndarray
    normal: np.ndarray

    @property
    def vertex_count(self) -> int:
        return len(self.distance)

    def mesh(self, flat: bool = False):
        """``(positions (N,3) f4, normals (N,3) f4, colours (N,4) u1, indices (3T,) u4)``,
        positions in world axes *relative to the frame centre* (``frame.center`` + position is
        the world point: float32 keeps its precision far from the world origin), normals in world
        space. ``flat=True`` puts every vertex on the plane through the centre (a flat billboard
        of the same maps, for comparison)."""
        f = self.frame
        ys, xs = np.nonzero(self.stencil)
        pc = f.pixel_centres()
        z = np.zeros(len(xs)) if flat else f.radius - self.distance.astype(np.float64)
        local = np.stack([pc[xs], pc[ys], z], axis=1)
        pos = local @ f.axes.T
        rgba = np.concatenate([self.color, np.full((len(xs), 1), 255, np.uint8)], axis=1)
        return pos.astype("f4"), self.normal.astype("f4"), rgba, grid_triangles(self.stencil)

    @property
    def triangle_count(self) -> int:
        return len(grid_triangles(self.stencil)) // 3


def angle_error_deg(board_dirs: np.ndarray, current_dirs: np.ndarray) -> np.ndarray:
    """Angle in degrees between (n, 3) board creation directions and current directions."""
    a = board_dirs / np.linalg.norm(board_dirs, axis=-1, keepdims=True)
    b = current_dirs / np.linalg.norm(current_dirs, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def _oct_encode(n: np.ndarray) -> np.ndarray:
    n = n / np.maximum(np.abs(n).sum(axis=1, keepdims=True), 1e-30)
    xy = n[:, :2].copy()
    neg = n[:, 2] < 0
    xy[neg] = (1 - np.abs(n[neg][:, ::-1][:, 1:])) * np.where(n[neg][:, :2] >= 0, 1.0, -1.0)
    return np.round(np.clip(xy, -1, 1) * 32767).astype("<i2")


def _oct_decode(e: np.ndarray) -> np.ndarray:
    xy = e.astype(np.float64) / 32767
    z = 1 - np.abs(xy).sum(axis=1)
    neg = z < 0
    xy[neg] = (1 - np.abs(xy[neg][:, ::-1])) * np.where(xy[neg] >= 0, 1.0, -1.0)
    n = np.concatenate([xy, z[:, None]], axis=1)
    return (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32)


def encode_board(b: Reliefboard) -> bytes:
    """Compact bytes of a board (see the module docstring for the layout)."""
    f = b.frame
    n = b.vertex_count
    head = _HEADER.pack(_MAGIC, int(b.object_id), f.size, n, f.radius, *f.center, *f.direction, 0.0)
    q = np.round(np.clip(b.distance / (2 * f.radius), 0, 1) * 65535).astype("<u2")
    parts = [head, np.packbits(b.stencil.ravel()).tobytes(), q.tobytes(),
             np.ascontiguousarray(b.color, np.uint8).tobytes(), _oct_encode(b.normal.astype(np.float64)).tobytes()]
    return b"".join(parts)


def decode_board(data: bytes) -> Reliefboard:
    """Inverse of :func:`encode_board` (distances to 2r/65535, normals to < 0.05°)."""
    if len(data) < _HEADER.size or data[:4] != _MAGIC:
        raise CorruptBlockError("Reliefboard message: bad header (not an RB01 board)")
    magic, oid, size, n, r, cx, cy, cz, dx, dy, dz, _ = _HEADER.unpack_from(data)
    frame = BoardFrame((cx, cy, cz), r, (dx, dy, dz), size)
    off = _HEADER.size
    nbits = (size * size + 7) // 8
    need = off + nbits + n * (2 + 3 + 4)
    if len(data) != need:
        raise CorruptBlockError(f"Reliefboard message for object {oid}: {len(data)} bytes, expected {need}")
    stencil = np.unpackbits(np.frombuffer(data, np.uint8, nbits, off))[: size * size].astype(bool).reshape(size, size)
    if int(stencil.sum()) != n:
        raise CorruptBlockError(f"Reliefboard message for object {oid}: stencil covers {int(stencil.sum())} pixels, header says {n}")
    off += nbits
    dist = np.frombuffer(data, "<u2", n, off).astype(np.float32) * np.float32(2 * r / 65535)
    off += 2 * n
    color = np.frombuffer(data, np.uint8, 3 * n, off).reshape(n, 3).copy()
    off += 3 * n
    normal = _oct_decode(np.frombuffer(data, "<i2", 2 * n, off).reshape(n, 2))
    return Reliefboard(int(oid), frame, stencil, dist, color, normal)
