"""The K-patch selection as it was before issue 20's LOD-stage rewrite, kept verbatim (only
the imports moved) as the baseline ``massview bench lod`` measures against and the reference
tests/test_lod_stage.py compares the new walk with: a triangle-by-triangle top-down walk with
per-level sorting to group diamonds (see :mod:`massview.lod.kpatch` for the model)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ...core.camera import Camera
from ...data.terrain.layout import TerrainLayout

__all__ = ["PatchHierarchy", "Front", "select_front", "patch_boxes", "lookup_blocks"]

Resident = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]  # (level, bi, bj) -> bool
Request = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]  # (level, bi, bj, priority)


class PatchHierarchy:
    """Per-diamond saturated errors, height ranges and nested bounding spheres (world units:
    x = col·dx, y = −row·dy, z = base + Z·(h·vertical_scale − base) with Z the view-time
    exaggeration and base the lowest scaled height, so errors scale by vertical_scale·Z)."""

    def __init__(self, layout: TerrainLayout, sq_err, dg_err, zmin, zmax, spacing=(1.0, 1.0), vscale: float = 1.0,
                 exaggeration: float = 1.0):
        self.lay = layout
        self.dx, self.dy = (float(v) for v in spacing)
        self.vs = float(vscale)
        self.exaggeration = Z = float(exaggeration)
        J = layout.J
        self.base = float(np.min(zmin[0])) * self.vs
        self.sq_err = [np.asarray(e, np.float64) * self.vs * Z for e in sq_err]
        self.dg_err = [np.asarray(e, np.float64) * self.vs * Z for e in dg_err]
        self.zmin = [self.base + Z * (np.asarray(z, np.float64) * self.vs - self.base) for z in zmin]
        self.zmax = [self.base + Z * (np.asarray(z, np.float64) * self.vs - self.base) for z in zmax]
        # edge-diamond height ranges: the union of the two squares beside the edge
        self.dg_zmin, self.dg_zmax = [], []
        for j in range(J):
            lo, hi = self._edge_range(self.zmin[j], np.inf, np.minimum), self._edge_range(self.zmax[j], -np.inf, np.maximum)
            self.dg_zmin.append(lo)
            self.dg_zmax.append(hi)
        self._spheres()

    @staticmethod
    def _edge_range(sq: np.ndarray, fill: float, op) -> np.ndarray:
        n = sq.shape[0]
        p = np.pad(sq, 1, constant_values=fill)
        out = np.full((2, n + 1, n + 1), fill)
        out[0, :, :n] = op(p[:-1, 1:-1], p[1:, 1:-1])  # horizontal edge v: squares v-1 and v
        out[1, :n, :] = op(p[1:-1, :-1], p[1:-1, 1:])  # vertical edge u: squares u-1 and u
        return out

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World box of the valid (non-padding) terrain."""
        lay = self.lay
        lo = np.array([0.0, -(lay.rows - 1) * self.dy, self.zmin[0].min()])
        hi = np.array([(lay.cols - 1) * self.dx, 0.0, self.zmax[0].max()])
        return lo, hi

    def _world(self, x, y, z):
        return np.stack([np.asarray(x, np.float64) * self.dx, -np.asarray(y, np.float64) * self.dy, z], axis=-1)

    def _spheres(self) -> None:
        lay, J = self.lay, self.lay.J
        half = lambda a: math.hypot(a / 2 * self.dx, a / 2 * self.dy)  # noqa: E731
        self.sq_c, self.sq_r, self.dg_c, self.dg_r = [None] * J, [None] * J, [None] * J, [None] * J
        for j in range(J - 1, -1, -1):
            a = lay.square_side(j)
            n = 2**j
            # edge diamonds (children: the 4 squares of level j+1 meeting at the midpoint)
            idx = np.arange(n + 1)
            valid = np.isfinite(self.dg_zmin[j])
            zc = np.where(valid, (np.where(valid, self.dg_zmin[j], 0) + np.where(valid, self.dg_zmax[j], 0)) / 2, 0.0)
            xs = np.stack([np.broadcast_to((idx[None, :] + 0.5) * a, (n + 1, n + 1)), np.broadcast_to(idx[None, :] * a, (n + 1, n + 1))])
            ys = np.stack([np.broadcast_to(idx[:, None] * a, (n + 1, n + 1)), np.broadcast_to((idx[:, None] + 0.5) * a, (n + 1, n + 1))])
            c = self._world(xs, ys, zc)
            r = np.sqrt(half(a) ** 2 + np.where(valid, (np.where(valid, self.dg_zmax[j], 0) - np.where(valid, self.dg_zmin[j], 0)) / 2, 0.0) ** 2)
            if j + 1 < J:
                r = np.maximum(r, self._edge_child_bound(c, n, self.sq_c[j + 1], self.sq_r[j + 1]))
            self.dg_c[j], self.dg_r[j] = c, r
            # square diamonds (children: the edge diamonds on their 4 sides)
            uu, vv = np.meshgrid(np.arange(n), np.arange(n))
            zc = (self.zmin[j] + self.zmax[j]) / 2
            c = self._world((uu + 0.5) * a, (vv + 0.5) * a, zc)
            r = np.sqrt(half(a) ** 2 + ((self.zmax[j] - self.zmin[j]) / 2) ** 2)
            for o, dv, du in ((0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 0, 1)):
                cc, rr = self.dg_c[j][o, dv:dv + n, du:du + n], self.dg_r[j][o, dv:dv + n, du:du + n]
                r = np.maximum(r, np.linalg.norm(c - cc, axis=-1) + rr)
            self.sq_c[j], self.sq_r[j] = c, r

    @staticmethod
    def _edge_child_bound(c: np.ndarray, n: int, kc: np.ndarray, kr: np.ndarray) -> np.ndarray:
        out = np.zeros(c.shape[:3])
        m = kc.shape[0]  # 2n
        for o in (0, 1):
            v, u = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
            if o == 0:  # horizontal edge (v, u): midpoint row 2v, col 2u+1 -> squares rows 2v-1..2v, cols 2u..2u+1
                rows, cols = (2 * v - 1, 2 * v), (2 * u, 2 * u + 1)
            else:
                rows, cols = (2 * v, 2 * v + 1), (2 * u - 1, 2 * u)
            for rr_ in rows:
                for cc_ in cols:
                    ok = (rr_ >= 0) & (rr_ < m) & (cc_ >= 0) & (cc_ < m)
                    ri, ci = np.clip(rr_, 0, m - 1), np.clip(cc_, 0, m - 1)
                    d = np.linalg.norm(c[o] - kc[ri, ci], axis=-1) + kr[ri, ci]
                    out[o] = np.maximum(out[o], np.where(ok, d, 0.0))
        return out


@dataclass
class Front:
    """Selected patches (one row each): apex/left/right vertices in finest-sample units
    (x = col, y = row), bintree depth, the block (level, bi, bj) they draw from, the sample
    stride inside that block, and the diamond z-range for culling."""

    ax: np.ndarray
    ay: np.ndarray
    lx: np.ndarray
    ly: np.ndarray
    rx: np.ndarray
    ry: np.ndarray
    depth: np.ndarray
    level: np.ndarray
    bi: np.ndarray
    bj: np.ndarray
    stride: np.ndarray
    zmin: np.ndarray
    zmax: np.ndarray
    deferred: int = 0  # diamonds that wanted to split but waited for data

    def __len__(self) -> int:
        return len(self.ax)

    def take(self, idx) -> "Front":
        f = {k: getattr(self, k)[idx] for k in ("ax", "ay", "lx", "ly", "rx", "ry", "depth", "level", "bi", "bj", "stride", "zmin", "zmax")}
        return Front(**f, deferred=self.deferred)


def lookup_blocks(grids: list[np.ndarray], level: np.ndarray, bi: np.ndarray, bj: np.ndarray) -> np.ndarray:
    """``grids[level[n]][bi[n], bj[n]]`` for every n: per-block values kept as one (nb, nb)
    grid per pyramid level (residency flags, GL slots ...)."""
    out = np.empty(len(level), grids[0].dtype if grids else bool)
    for lv in np.unique(level):
        sel = level == lv
        out[sel] = grids[lv][bi[sel], bj[sel]]
    return out


def _draw_level(lay: TerrainLayout, depth: np.ndarray) -> np.ndarray:
    """Sample level a patch at ``depth`` uses (may exceed L)."""
    j = depth // 2
    return np.where(depth % 2 == 0, lay.J - j, lay.J - j - 1)


def _blocks_for(lay: TerrainLayout, depth: np.ndarray, cx: np.ndarray, cy: np.ndarray):
    lvl = _draw_level(lay, depth)
    blvl = np.minimum(lvl, lay.L)
    span = (lay.M - 1) * (2 ** blvl)
    return blvl, cy // span, cx // span, 2 ** (lvl - blvl)


def _diamond_lookup(h: PatchHierarchy, t: int, lx, ly, rx, ry):
    """(key, err, center, radius, zmin, zmax, expected-count) of the hypotenuse diamond of
    triangles at depth t."""
    lay = h.lay
    j = t // 2
    a = lay.square_side(j)
    mx, my = (lx + rx) // 2, (ly + ry) // 2
    if t % 2 == 0:
        v, u = (my - a // 2) // a, (mx - a // 2) // a
        key = v * (2**j) + u
        if j < lay.J:
            return key, h.sq_err[j][v, u], h.sq_c[j][v, u], h.sq_r[j][v, u], h.zmin[j][v, u], h.zmax[j][v, u], np.full(len(v), 2)
        return key, None, None, None, h.zmin[j][v, u], h.zmax[j][v, u], None
    horiz = ly == ry
    o = np.where(horiz, 0, 1)
    v = np.where(horiz, my // a, (my - a // 2) // a)
    u = np.where(horiz, (mx - a // 2) // a, mx // a)
    n = 2**j
    key = (o * (n + 1) + v) * (n + 1) + u
    border = np.where(horiz, (v == 0) | (v == n), (u == 0) | (u == n))
    return (key, h.dg_err[j][o, v, u], h.dg_c[j][o, v, u], h.dg_r[j][o, v, u], h.dg_zmin[j][o, v, u], h.dg_zmax[j][o, v, u],
            np.where(border, 1, 2))


def _group_all(key: np.ndarray, flag: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """Per element: every element sharing its key has ``flag`` and the group has ``expected`` members."""
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    counts = np.diff(np.r_[start, len(ks)])
    allf = np.logical_and.reduceat(flag[order], start) if len(ks) else np.zeros(0, bool)
    ok_group = allf & (counts == expected[order][start])
    out = np.empty(len(key), bool)
    out[order] = np.repeat(ok_group, counts)
    return out


class _Projector:
    """Pixels a unit vertical segment can move anywhere in a sphere (see module docstring)."""

    def __init__(self, camera: Camera):
        self.f = camera.height / 2 / math.tan(math.radians(camera.fovy) / 2)
        v = camera.view_matrix()
        self.rot, self.t = v[:3, :3], v[:3, 3]
        self.u = np.abs(self.rot[:, 2])  # world up in camera axes

    def gain(self, c: np.ndarray, r: np.ndarray) -> np.ndarray:
        p = c @ self.rot.T + self.t
        zlo = -p[:, 2] - r  # nearest depth in the sphere
        ok = zlo > 0
        z = np.where(ok, zlo, 1.0)
        a, b = (np.abs(p[:, 0]) + r) / z, (np.abs(p[:, 1]) + r) / z
        ux, uy, uz = self.u
        g = self.f * np.hypot(ux + a * uz, uy + b * uz) / z
        return np.where(ok, g, np.inf)


def select_front(h: PatchHierarchy, camera: Camera, tau: float = 1.0, resident: Resident | None = None,
                 request: Request | None = None) -> Front:
    """The conforming K-patch cut for ``camera`` (a pure function of the camera, the data and
    ``resident``). Patches outside the frustum are kept (their parents decide conformity)
    but not refined; cull them per viewport with :func:`patch_boxes`."""
    lay = h.lay
    A = lay.S - 1
    ax = np.array([A, 0], np.int64)
    ay = np.array([0, A], np.int64)
    lx = np.array([0, A], np.int64)
    ly = np.array([0, A], np.int64)
    rx = np.array([A, 0], np.int64)
    ry = np.array([A, 0], np.int64)
    proj = _Projector(camera)
    planes = camera.frustum_planes()
    parts, deferred = [], 0
    for t in range(2 * lay.J + 1):
        depth = np.full(len(ax), t)
        key, err, c, r, zlo, zhi, expected = _diamond_lookup(h, t, lx, ly, rx, ry)
        if err is None or len(ax) == 0:  # deepest level: leaves
            parts.append((ax, ay, lx, ly, rx, ry, depth, zlo, zhi))
            break
        inside = np.all(c @ planes[:, :3].T + planes[:, 3] >= -r[:, None], axis=1)
        with np.errstate(invalid="ignore"):  # 0 · inf (exact patch touching the eye) is 0
            pix = np.nan_to_num(err * proj.gain(c, r), nan=0.0)  # pixel-error bound over the sphere
        crit = inside & (pix > tau)
        want = crit
        if resident is not None:
            cx, cy = (ax + lx + rx) // 3, (ay + ly + ry) // 3
            blvl, bi, bj, _ = _blocks_for(lay, depth + 1, cx, cy)
            res = resident(blvl, bi, bj)
            miss = crit & ~res
            if request is not None and miss.any():
                request(blvl[miss], bi[miss], bj[miss], np.minimum(pix[miss], 1e30))
            want = crit & res
        split = _group_all(key, want, expected)
        deferred += int(np.count_nonzero(crit & ~split))
        keep = ~split
        parts.append((ax[keep], ay[keep], lx[keep], ly[keep], rx[keep], ry[keep], depth[keep], zlo[keep], zhi[keep]))
        sx, sy, slx, sly, srx, sry = ax[split], ay[split], lx[split], ly[split], rx[split], ry[split]
        mx, my = (slx + srx) // 2, (sly + sry) // 2
        # children (apex m; hypotenuses are the parent's legs): (m, l, apex) and (m, apex, r)
        ax, ay = np.r_[mx, mx], np.r_[my, my]
        lx, ly = np.r_[slx, sx], np.r_[sly, sy]
        rx, ry = np.r_[sx, srx], np.r_[sy, sry]
    cols = [np.concatenate([p[i] for p in parts]) for i in range(9)]
    ax, ay, lx, ly, rx, ry, depth, zlo, zhi = cols
    cx, cy = (ax + lx + rx) // 3, (ay + ly + ry) // 3
    blvl, bi, bj, stride = _blocks_for(lay, depth, cx, cy)
    return Front(ax, ay, lx, ly, rx, ry, depth, blvl, bi, bj, stride, zlo, zhi, deferred)


def patch_boxes(h: PatchHierarchy, f: Front) -> tuple[np.ndarray, np.ndarray]:
    """World-space axis-aligned boxes (lo, hi), (n, 3) each, bounding every patch."""
    xs = np.stack([f.ax, f.lx, f.rx]) * h.dx
    ys = -np.stack([f.ay, f.ly, f.ry]) * h.dy
    lo = np.stack([xs.min(0), ys.min(0), f.zmin], axis=1)
    hi = np.stack([xs.max(0), ys.max(0), f.zmax], axis=1)
    return lo, hi


class BaselineStage:
    """T1's whole LOD stage of a frame as it was before issue 20 (``systems/terrain.py``,
    asynchronous loading): shading wants and residency as Python sets of (level, i, j) tuples,
    the agreement, the triangle walk above, front bookkeeping, box culling of the whole front
    and the task's share. It runs on a :class:`~massview.systems.terrain.TerrainSystem`'s GL
    pool and block cache (shared with the new stage) with its own front and wanted set."""

    def __init__(self, system):
        from ...lod.texlod import shading_blocks

        self.sys, self._shading_blocks = system, shading_blocks
        st = system.store
        self.h = PatchHierarchy(system.lay, *st.lod_arrays(), spacing=st.spacing, vscale=st.vertical_scale)
        self._minmax = [st.block_minmax(lv) for lv in range(system.lay.levels)]
        self.front, self._tex, self._wanted = None, set(), set()

    def _front_keys(self) -> set:
        f = self.front
        if f is None or len(f) == 0:
            return set()
        return set(zip(f.level.tolist(), f.bi.tolist(), f.bj.tolist()))

    def _request(self, lv, bi, bj, prio) -> None:
        for key, p in zip(zip(lv.tolist(), bi.tolist(), bj.tolist()), prio.tolist()):
            self._wanted.add(key)
            self.sys.cache.request(key, p)

    def _want_shading(self, camera) -> None:
        s, h = self.sys, self.h
        lv, bi, bj, prio = self._shading_blocks(self._minmax, s.lay.M, s.store.spacing,
                                                lambda z: h.base + h.exaggeration * (z * h.vs - h.base), camera)
        self._tex = set(zip(lv.tolist(), bi.tolist(), bj.tolist()))
        _, pool, _, _ = s.renderers()
        for key, p in zip(zip(lv.tolist(), bi.tolist(), bj.tolist()), prio.tolist()):
            if not pool.resident[key[0]][key[1], key[2]]:
                self._wanted.add(key)
                s.cache.request(key, 1e-6 * p)

    def _upload_ready(self, pool, keep: set) -> int:
        n = 0
        for key in list(self._wanted):
            if pool.resident[key[0]][key[1], key[2]]:
                self._wanted.discard(key)
                continue
            verts = self.sys.cache.get(key)
            if verts is not None:
                span = (self.sys.lay.M - 1) << key[0]
                if pool.upload(key, verts, (key[1] * span, key[2] * span), 2 ** key[0], keep):
                    self._wanted.discard(key)
                    n += 1
        return n

    def prepare_frame(self, comm, camera, cfg) -> None:
        from ...parallel.exchange import agree_all

        s = self.sys
        _, pool, terrain, _ = s.renderers()
        s.cache.begin_frame()
        self._want_shading(camera)
        self._upload_ready(pool, self._front_keys() | self._tex)
        flat = np.concatenate([g.ravel() for g in pool.resident])
        agreed = agree_all(comm, flat)
        grids, o = [], 0
        for g in pool.resident:
            grids.append(agreed[o:o + g.size].reshape(g.shape))
            o += g.size
        front = select_front(self.h, camera, cfg.tau, lambda lv, bi, bj: lookup_blocks(grids, lv, bi, bj), self._request)
        self.front = front
        terrain.set_pages(pool.page_table(grids))
        pool.touch(self._front_keys() | self._tex)

    def select(self, task, camera) -> "Front":
        """The task's share of the front (sort-first tiles and the whole frame: box culling)."""
        from ...lod.cull import boxes_in_frustum

        full = task.viewport == camera.viewport
        lo, hi = patch_boxes(self.h, self.front)
        vis = np.flatnonzero(boxes_in_frustum(lo, hi, camera.frustum_planes(None if full else task.viewport)))
        return self.front.take(vis)
