"""The K-patch cut as a walk over diamonds, level by level (the engine of
:func:`massview.lod.kpatch.select_front`; RASTeR, Bösch et al. 2009 §3, Goswami et al. 2010 §4.2).

Every bintree depth t holds *diamonds* (square diamonds (j, v, u) at t = 2j, edge diamonds
(j, o, v, u) at t = 2j + 1, see :mod:`massview.data.terrain.layout`), each made of two
triangles, its *halves*. Half 0 of a square comes from splitting its horizontal parent edge,
half 1 from its vertical one; half 0 of an edge lies in the square above (o = 0) or left
(o = 1) of it, half 1 in the square below or right. A half is *present* when its parent
diamond split; a diamond splits when

* it is *critical*: its sphere touches the view frustum (six planes, or the tile's sub-frustum)
  and its error bound projects to more than τ pixels (:class:`View`),
* the blocks each present half's children draw from are resident, and
* it is *complete*: every half that exists inside the domain is present.

This is the same rule as a triangle-by-triangle walk with its per-diamond grouping, evaluated
once per diamond instead of once per triangle, with integer (v, u) arithmetic in place of
vertex bookkeeping, and a reusable mark array in place of sorting to pair the halves a
diamond receives from its two parents. Everything is elementwise numpy (no BLAS), so a
diamond's decision does not depend on which other diamonds share its batch: a tile's walk
and the whole frame's walk decide every diamond they both reach identically.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.camera import Camera, Viewport
from .kernels import lod_kernels

__all__ = ["Dims", "View", "Residency", "square_halves", "edge_halves", "merge_halves", "draw_level", "edge_exists", "patch_vertices"]


class Dims:
    """The layout's integers as plain attributes (a :class:`TerrainLayout` derives them with
    logarithms on every access; the walk reads them hundreds of times a frame)."""

    def __init__(self, lay):
        self.n, self.m, self.J, self.L, self.M, self.levels = lay.n, lay.m, lay.J, lay.L, lay.M, lay.levels

    def square_side(self, j: int) -> int:
        return 1 << (self.n - j)


class View:
    """Per-camera constants of the split test, in camera space (x right, y up, looking down −z).

    ``test(xyz, r, err)`` for spheres (world centres (3, n), radii) and saturated errors (world
    units), all float64, returns (critical, pixel error, code) with code 0 = the sphere is
    outside a frustum plane, 1 = it crosses one, 2 = it is inside all six. The frustum is the
    camera's, or the off-axis sub-frustum of ``viewport`` (sort-first tiles). The pixel bound
    is the module docstring's of :mod:`massview.lod.kpatch`: f·e·√((|u_x| + a|u_z|)² +
    (|u_y| + b|u_z|)²)/(z_c − r).

    Every operation is elementwise over the spheres (the three-term rotation sums reduce an
    rotation rows add in order, ((r₀x + r₁y) + r₂z) + t), so a sphere's result never depends
    on its batch; the work is a few dozen whole-array calls per batch."""

    def __init__(self, camera: Camera, tau: float, viewport: Viewport | None = None, kernel: str | None = None):
        self.tau = float(tau)
        self.kernel = lod_kernels(kernel)
        self.f = camera.height / 2 / math.tan(math.radians(camera.fovy) / 2)
        v = camera.view_matrix()
        self.rot = [[float(x) for x in row] for row in v[:3, :3]]
        self.t = [float(x) for x in v[:3, 3]]
        self.ux, self.uy, self.uz = (float(x) for x in np.abs(v[:3, 2]))
        left, right, bottom, top = camera.window(viewport)
        n = camera.near
        # side planes through the eye, inward unit normals (x or y, z components)
        self.sides_x = [(n / math.hypot(n, left), left / math.hypot(n, left)),
                        (-n / math.hypot(n, right), -right / math.hypot(n, right))]
        self.sides_y = [(n / math.hypot(n, bottom), bottom / math.hypot(n, bottom)),
                        (-n / math.hypot(n, top), -top / math.hypot(n, top))]
        self.near, self.far = float(camera.near), float(camera.far)
        self._rot = np.array(self.rot)[:, :, None]  # (3, 3, 1): column k of the rotation as (3, 1)
        self._t = np.array(self.t)[:, None]
        sides = self.sides_x + self.sides_y
        self._side_a = np.array([a for a, _ in sides])[:, None]  # on x, x, y, y
        self._side_c = np.array([c for _, c in sides])[:, None]  # on z
        self._u = np.array([self.ux, self.uy])[:, None]
        self._consts = (np.array(self.rot), np.array(self.t), self._side_a[:, 0].copy(), self._side_c[:, 0].copy(), self.near, self.far)
        self.kernel_consts = (*self._consts, self._u[:, 0].copy(), self.uz, self.f, self.tau)  # the kernels' arguments

    def camera_space(self, x, y, z):
        (a, b, c), (d, e, f), (g, h, i) = self.rot
        tx, ty, tz = self.t
        return a * x + b * y + c * z + tx, d * x + e * y + f * z + ty, g * x + h * y + i * z + tz

    def to_camera(self, xyz: np.ndarray) -> np.ndarray:
        """(3, n) world points to camera space, the same float64 values as :meth:`camera_space`."""
        p = self._rot[:, 0] * xyz[0]
        q = self._rot[:, 1] * xyz[1]
        p += q
        np.multiply(self._rot[:, 2], xyz[2], out=q)
        p += q
        p += self._t
        return p

    def code(self, px, py, pz, r) -> np.ndarray:
        """0 outside a plane, 1 crossing, 2 inside all (spheres in camera space)."""
        inside, full = self._planes(np.stack([px, py, pz]), r)
        return inside.view(np.int8) + full.view(np.int8)

    def _planes(self, p: np.ndarray, r):
        """(touches every plane, inside every plane) for spheres at camera-space ``p`` (3, n):
        the least signed distance of the centre to the six planes against ∓r."""
        pz = p[2]
        d = np.empty((4, p.shape[1]))
        np.multiply(p[0], self._side_a[:2], out=d[:2])  # x·a on the two x planes, y·a on the two y planes
        np.multiply(p[1], self._side_a[2:], out=d[2:])
        d += np.multiply(pz, self._side_c)
        m = d.min(axis=0)
        np.minimum(m, pz + self.far, out=m)
        near = np.negative(pz)
        near -= self.near
        np.minimum(m, near, out=m)
        return m >= np.negative(r), m >= r

    def test(self, xyz, r, err):
        if self.kernel is not None:
            n = xyz.shape[1]
            crit, pix, code = np.empty(n, bool), np.empty(n), np.empty(n, np.int8)
            self.kernel.split_test(xyz[0], xyz[1], xyz[2], r, err, *self.kernel_consts, crit, pix, code)
            return crit, pix, code
        p = self.to_camera(xyz)
        inside, full = self._planes(p, r)
        zlo = np.negative(p[2])
        zlo -= r  # nearest depth in the sphere
        ok = zlo > 0
        every = bool(ok.all())
        zz = zlo if every else np.where(ok, zlo, 1.0)
        ab = np.abs(p[:2])  # a, b: the off-axis slopes over the sphere
        ab += r
        ab /= zz
        ab *= self.uz
        ab += self._u
        ab *= ab
        g = np.add(ab[0], ab[1])
        np.sqrt(g, out=g)
        g *= self.f
        g /= zz
        if every:
            pix = g
            pix *= err
        else:
            with np.errstate(invalid="ignore"):  # 0 · inf (exact patch touching the eye) is 0
                pix = err * np.where(ok, g, np.inf)
            pix[np.isnan(pix)] = 0.0
        code = inside.view(np.int8) + full.view(np.int8)
        inside &= pix > self.tau
        return inside, pix, code


class Residency:
    """Which blocks the walk may refine into: ``None`` (all), a list of per-level (nb, nb) bool
    grids (agreed by every rank), or a callable ``(level, bi, bj) -> bool`` over arrays."""

    def __init__(self, resident, levels: int, top: int):
        self.fn = self.flat = None
        if callable(resident):
            self.fn = resident
        elif resident is not None:
            self.flat = _flat_view(resident)
            if self.flat is None:
                self.flat = np.concatenate([np.asarray(g, bool).ravel() for g in resident])
            self.offset = np.cumsum([0] + [np.asarray(g).size for g in resident])
            self.nb = [np.asarray(g).shape[1] for g in resident]
            self.level_all = [bool(np.asarray(g).all()) for g in resident]

    @property
    def all(self) -> bool:
        return self.fn is None and (self.flat is None or all(self.level_all))

    def level_resident(self, blvl: int) -> bool:
        """Every block of level ``blvl`` is resident (the lookups can be skipped)."""
        return self.fn is None and (self.flat is None or self.level_all[blvl])

    def lookup(self, blvl: int, bi: np.ndarray, bj: np.ndarray, nb: int) -> np.ndarray:
        """Agreed residency of blocks (blvl, bi, bj) of a level with ``nb`` per side; indices
        just outside the level (the absent half of a border edge) read an arbitrary flag, which
        the caller masks."""
        if self.fn is not None:
            return np.asarray(self.fn(np.full(len(bi), blvl), np.clip(bi, 0, nb - 1), np.clip(bj, 0, nb - 1)), bool)
        return self.flat.take(self.offset[blvl] + bi * nb + bj, mode="clip")


def _flat_view(grids):
    """The flat bool array the per-level ``grids`` are consecutive views of (as
    :meth:`massview.lod.blockindex.BlockIndex.grids` makes them), or None."""
    base = getattr(grids[0], "base", None) if len(grids) else None
    if not isinstance(base, np.ndarray) or base.ndim != 1 or base.dtype != bool or not base.flags.c_contiguous:
        return None
    at = base.__array_interface__["data"][0]
    for g in grids:
        if g.base is not base or not g.flags.c_contiguous or g.__array_interface__["data"][0] != at:
            return None
        at += g.size
    return base if at == base.__array_interface__["data"][0] + base.size else None


def square_halves(v, u, a: int):
    """Apexes (x, y) of halves 0 and 1 of square diamonds (v, u) of side ``a`` and the sum of
    their hypotenuse (diagonal) endpoints, in finest-sample units."""
    x0, y0 = u * a, v * a
    ou, ov = u & 1, v & 1
    return (x0 + a - a * ou, y0 + a * ov), (x0 + a * ou, y0 + a - a * ov), (2 * x0 + a, 2 * y0 + a)


def edge_halves(o, v, u, a: int):
    """Apexes of halves 0 and 1 of edge diamonds (o, v, u) of length ``a`` and the sum of
    their hypotenuse (the edge) endpoints."""
    x0, y0 = u * a, v * a
    h = a // 2
    return (x0 + h - a * o, y0 + h - a * (1 - o)), (x0 + h, y0 + h), (2 * x0 + a * (1 - o), 2 * y0 + a * o)


def merge_halves(mark: np.ndarray, id0: np.ndarray, id1: np.ndarray):
    """Union of two duplicate-free id lists (receivers of half 0 and of half 1): the union is
    id0 followed by ``id1[only1]``; ``in1`` flags the id0 entries also in id1 (both halves
    present). ``mark`` is a zeroed uint8 scratch at least as long as the level's id range; it
    is left zeroed. O(len) with no sorting."""
    mark[id1] = 1
    in1 = mark[id0].view(bool)
    mark[id1] = 0
    mark[id0] = 1
    only1 = mark[id1] == 0
    mark[id0] = 0
    return in1, only1


def draw_level(J: int, t: int) -> int:
    """Sample level a patch at bintree depth ``t`` uses (may exceed L)."""
    return J - t // 2 if t % 2 == 0 else J - t // 2 - 1


def edge_exists(o, v, u, n: int):
    """Whether halves 0 and 1 of edge diamonds (o, v, u) at a level with n squares per side
    lie inside the domain (border edges have one)."""
    w = np.where(o == 0, v, u)
    return w >= 1, w < n


def patch_vertices(t: int, o, v, u, half, a: int):
    """(ax, ay, lx, ly, rx, ry) of the halves ``half`` (bool: half 1) of diamonds at depth t,
    oriented as the top-down split produces them: (l − a) × (r − a) < 0 at even depths, > 0 at
    odd ones (each split reverses the winding)."""
    if t % 2 == 0:
        (a0x, a0y), (a1x, a1y), _ = square_halves(v, u, a)
        x0, y0 = u * a, v * a
        odd = (u + v) & 1
        px, py = x0 + a * odd, y0
        qx, qy = x0 + a - a * odd, y0 + a
    else:
        (a0x, a0y), (a1x, a1y), _ = edge_halves(o, v, u, a)
        px, py = u * a, v * a
        qx, qy = px + a * (1 - o), py + a * o
    ax, ay = np.where(half, a1x, a0x), np.where(half, a1y, a0y)
    cross = (px - ax) * (qy - ay) - (py - ay) * (qx - ax)
    swap = (cross < 0) != (t % 2 == 0)
    lx, ly = np.where(swap, qx, px), np.where(swap, qy, py)
    rx, ry = np.where(swap, px, qx), np.where(swap, py, qy)
    return ax, ay, lx, ly, rx, ry
