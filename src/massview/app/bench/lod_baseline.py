"""The K-patch selection as it was before issue 20's LOD-stage rewrite, kept verbatim (only
the imports moved) as the baseline ``massview bench lod`` measures against and the reference
tests/test_lod_stage.py compares the new walk with: a triangle-by-triangle top-down walk with
per-level sorting to group diamonds (see :mod:`massview.lod.kpatch` for the model). The
hierarchy, the :class:`Front` and the block lookups it walks over are :mod:`massview.lod.kpatch`'s
own: only the walk is the old one."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ...core.camera import Camera
from ...data.terrain.layout import TerrainLayout
from ...lod import kpatch
from ...lod.kpatch import Front, lookup_blocks, patch_boxes

__all__ = ["PatchHierarchy", "Front", "select_front", "patch_boxes", "lookup_blocks"]

Resident = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]  # (level, bi, bj) -> bool
Request = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]  # (level, bi, bj, priority)


class PatchHierarchy(kpatch.PatchHierarchy):
    """:class:`massview.lod.kpatch.PatchHierarchy` (the same errors, height ranges and spheres)
    keeping the (…, 3) sphere centres ``sq_c``/``dg_c`` the old walk reads, without the flat
    tables the new walk builds from them."""

    def _tables(self) -> None:
        pass


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
