"""Drawing terrain K-patches (RASTeR's rendering side).

* :class:`BlockPool` (:mod:`.terrain_pool`, re-exported with :func:`pack_payload`) keeps
  resident blocks in fixed GL slots: heights in one vertex buffer, shading maps and
  orthophoto colour in texture arrays.
* K-patch index patterns are static: one per patch shape (orientation × sample step),
  generated once by uniform refinement and shared by all blocks; a patch is drawn with
  ``baseVertex`` = its block slot and anchor sample, ``baseInstance`` = the slot.
* :meth:`TerrainRenderer.draw` issues the whole front as one
  ``glMultiDrawElementsIndirect``: a command per patch, except that a block the front covers
  whole at its level is one command of a merged pattern (at full resolution: 256 commands
  instead of 131 072 on a 4097² DEM; llvmpipe pays state, mapping and a pipeline flush per
  command). Shading is per pixel and independent of the geometric LOD: a page table (one
  texel per block of every level: its slot, or -1) lets the fragment stage read the shading
  pyramid at the level matching the pixel footprint (terrain_shading.glsl). Shading is
  forward or deferred (:mod:`.terrain_gbuffer`: the geometry pass writes the shading's inputs,
  one full-screen pass shades each pixel once), bit-identical either way, chosen per draw by
  triangles per target pixel (:data:`DEFERRED_ABOVE`).
* Back faces are culled when the eye is above the terrain (:meth:`TerrainRenderer._cull`).
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from ..lod.kpatch import lookup_blocks, refine_uniform
from .colormaps import LIGHT_WEIGHTS, Shading, haze_start
from .terrain_gbuffer import GBuffers
from .terrain_pool import BlockPool, layer_bytes, pack_payload, payload_bytes, payload_parts
from .terrain_programs import TerrainPrograms, program
from .terrain_plain import VERTEX_BYTES, PlainMeshRenderer, pack_block  # noqa: F401  (re-exported)

# Deferred shading pays a full-screen pass and a G-buffer; forward shading pays the shading on
# every 4×4 stamp a triangle touches. The shading pass skips sky pixels (a far-plane triangle,
# depth test GREATER) and commands go front to back, so deferred pays from fewer triangles a
# pixel than before (0.3). Measured on llvmpipe under load (issue 20, CPU-ms of a draw, median
# of 3, demo 4097² flyover cameras at 1280×1024, whole fronts and halves/quarters/eighths of
# them, τ 0.5–32): deferred ÷ forward 0.67–0.80 at 0.19–0.95 triangles a pixel, 0.81–0.93 at
# 0.049–0.17, 0.97 at 0.045, 1.03 at 0.038, 1.01–1.29 at 0.012–0.032, 1.3–2.1 below 0.011.
# Deferred above this many triangles a pixel.
DEFERRED_ABOVE = 0.04

__all__ = ["DEFERRED_ABOVE", "VERTEX_BYTES", "pack_block", "pack_payload", "payload_bytes", "payload_parts", "layer_bytes", "BlockPool", "TerrainRenderer", "PlainMeshRenderer"]



def _distinct_rows(rows: np.ndarray, radix: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0, return_inverse=True)`` for an (n, c) integer array whose
    entries lie in [0, radix): each row is read as one int64 of c base-``radix`` digits (same
    order), falling back to ``np.unique`` where that number could overflow."""
    n, c = rows.shape
    if n == 0 or radix ** c >= 2 ** 62:
        uniq, inv = np.unique(rows, axis=0, return_inverse=True)
        return uniq, inv.ravel()
    key = rows[:, 0].astype(np.int64)
    for j in range(1, c):
        key = key * radix + rows[:, j]
    ukey = np.unique(key)
    inv = np.searchsorted(ukey, key)
    uniq = np.empty((len(ukey), c), np.int64)
    rest = ukey
    for j in range(c - 1, -1, -1):
        rest, uniq[:, j] = np.divmod(rest, radix)
    return uniq, inv


def _stable_order(slots: np.ndarray) -> np.ndarray:
    """``np.argsort(slots, kind="stable")`` for GL slot numbers (non-negative), on 16 bits where
    they fit: numpy sorts those by radix, several times faster than int64."""
    if len(slots) and int(slots.max()) < 1 << 16:
        slots = slots.astype(np.uint16)
    return np.argsort(slots, kind="stable")


def _facing_up(tri: np.ndarray) -> np.ndarray:
    """(n, 3, 2) triangles in (col, row) samples, each ordered counter-clockwise seen from
    above in world axes (x = col·dx, y = −row·dy): front-facing (GL's default, CCW) wherever
    the surface faces the eye, so back faces can be culled (:meth:`TerrainRenderer._cull`)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    cw = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0  # counter-clockwise in (col, row): clockwise in world x, y
    out = tri.copy()
    out[cw, 1], out[cw, 2] = tri[cw, 2], tri[cw, 1]
    return out


def _front_to_back(distance: np.ndarray) -> np.ndarray:
    """The order that draws commands nearest first (stable: ties keep their order). Drawing near
    surfaces first lets the depth test, which llvmpipe runs before the fragment shader, reject
    what they hide. A depth test LESS keeps the nearest fragment whatever the order, so only an
    exact depth tie between two triangles at one pixel could change; none does on the golden,
    side-by-side and demo frames (tests/test_terrain_draw.py)."""
    return np.argsort(distance, kind="stable")


class TerrainRenderer:
    """Draws fronts from ``pool`` with per-pixel shading. ``base`` is the lowest scaled height
    (exaggeration pivots on it), ``world_size`` the terrain's horizontal diagonal (haze scale).
    ``deferred``: True shades in a second, per-pixel pass (:mod:`.terrain_gbuffer`), False
    per fragment (forward; the same bytes), None (default) picks per draw: deferred above
    :data:`DEFERRED_ABOVE` triangles per pixel of the target's scissor (or viewport);
    ``used_deferred`` tells what the last draw did. ``merge``
    (default) draws every block the front covers whole with one command (:meth:`_commands`);
    ``False`` keeps one command per patch. ``sort`` (default) issues the commands front to back
    (:func:`_front_to_back`) so that llvmpipe's early depth test rejects hidden fragments;
    ``False`` keeps front order."""

    def __init__(self, ctx: moderngl.Context, pool: BlockPool, k: int, spacing, vscale: float, extent: tuple[int, int],
                 base: float = 0.0, world_size: float = 1.0, deferred: bool | None = None, merge: bool = True,
                 peak: float = math.inf, sort: bool = True):
        self.ctx, self.pool, self.k, self.deferred, self.merge, self.sort = ctx, pool, k, deferred, bool(merge), bool(sort)
        self._spacing = (float(spacing[0]), float(spacing[1]))
        self.used_deferred = False
        self.vscale, self.base, self.world_size, self.peak = float(vscale), float(base), float(world_size), float(peak)
        self._footprint = ((extent[1] - 1) * float(spacing[0]), (extent[0] - 1) * float(spacing[1]))
        top = len(pool.slot_of) - 1
        side = (pool.M - 1) * 2**top + 1  # samples a side, padding included
        self.programs = TerrainPrograms(ctx, pool.M, padded=extent[0] < side or extent[1] < side)
        self._shade_vao = ctx.vertex_array(self.programs.shade, [])
        self._gbuffers = GBuffers(ctx)
        self._uniform("u_scale", (float(spacing[0]), float(spacing[1]), float(vscale)))
        self._uniform("u_spacing", (float(spacing[0]), float(spacing[1])))
        self._uniform("u_extent", (float(extent[1] - 1), float(extent[0] - 1)))
        self._uniform("u_top", top)
        rows = np.cumsum([0] + [g.shape[0] for g in pool.slot_of])[:-1]
        self._uniform("u_pagerow", tuple(int(v) for v in rows) + (0,) * (16 - len(rows)))
        for name, unit in (("u_shade", 0), ("u_ortho", 1), ("u_pages", 2), ("u_ramp", 3), ("u_g0", 4)):
            self._uniform(name, unit)
        nb0 = pool.slot_of[0].shape[0]
        self._pages = ctx.texture((nb0, sum(g.shape[0] for g in pool.slot_of)), 1, dtype="i4")
        self._pages.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._ramp = ctx.texture((256, 1), 3, dtype="f1")
        self._ramp.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._ramp.repeat_x = self._ramp.repeat_y = False
        self.set_pages(pool.page_table())
        self.set_shading(Shading())
        self._patterns: dict[tuple, int] = {}
        self._pattern_data: list[np.ndarray] = []
        self._merged: dict[bytes, int] = {}  # whole-block patterns: sorted (pattern, anchor) keys -> id
        self._merged_data: list[np.ndarray] = []
        self._merged_first = np.zeros(0, np.int64)
        self._ibo = None
        self.vao = self._gvao = None
        self._indirect = None
        self.tris_per_patch = 4**k
        self.draws = 0  # commands in the last draw

    def set_pages(self, table: np.ndarray) -> None:
        """Which blocks the fragment stage may read (:meth:`BlockPool.page_table`)."""
        self._pages.write(np.ascontiguousarray(table, np.int32).tobytes())

    def set_shading(self, sh: Shading) -> None:
        from .colormaps import SKY_HORIZON, SKY_ZENITH, ramp

        if getattr(self, "shading", None) == sh:
            return
        self.shading = sh
        u = self._uniform
        u("u_exag", (self.base, float(sh.exaggeration)))
        u("u_slope_scale", self.vscale * float(sh.exaggeration))
        u("u_sun", sh.sun_vector())
        u("u_light", LIGHT_WEIGHTS)
        if self.programs.set_mode(1 if sh.colormap == "ortho" and self.pool.has_ortho else (2 if sh.colormap in ("none", "ortho") else 0)):
            self._shade_vao.release()
            self._shade_vao = self.ctx.vertex_array(self.programs.shade, [])
            if getattr(self, "_ibo", None) is not None:
                self._rebuild()
        u("u_haze", sh.extinction(self.world_size))
        self._ramp.write(ramp(sh.colormap).tobytes())
        u("u_sky_horizon", SKY_HORIZON)
        u("u_sky_zenith", SKY_ZENITH)

    def haze_from(self, eye) -> float:
        """Where haze starts (:func:`.colormaps.haze_start`) for the terrain's box at the
        shading's exaggeration."""
        fx, fy = self._footprint
        Z = float(getattr(getattr(self, "shading", None), "exaggeration", 1.0))
        zhi = self.base + Z * (self.peak - self.base) if math.isfinite(self.peak) else math.inf
        return haze_start(eye, (0.0, -fy, self.base), (fx, 0.0, zhi), self.world_size)

    def _uniform(self, name: str, value) -> None:
        """Set a uniform in every program that has it (:class:`.terrain_programs.TerrainPrograms`)."""
        self.programs.set(name, value)

    def world_vertices(self, key: tuple[int, int, int]) -> np.ndarray:
        """(M·M, 3) float32 world positions the vertex stage gives the samples of resident block
        ``key`` (transform feedback through terrain.vert.glsl with the current uniforms)."""
        pool, M = self.pool, self.pool.M
        s = pool.slots[key]
        prog = program(self.ctx, "terrain.vert.glsl", None, self.programs.defines, varyings=["v_world"])
        for name in ("u_scale", "u_exag"):
            prog[name].value = self.programs.get(name)
        inst = self.ctx.buffer(np.frombuffer(pool.inst.read(16, offset=s * 16), np.int32).tobytes())
        vao = self.ctx.vertex_array(prog, [(pool.vbo, "f", "in_h"), (inst, "4i/i", "in_slot")])
        out = self.ctx.buffer(reserve=M * M * 12)
        vao.transform(out, mode=moderngl.POINTS, vertices=M * M, first=s * M * M)
        pos = np.frombuffer(out.read(), np.float32).reshape(M * M, 3).copy()
        for o in (out, vao, inst, prog):
            o.release()
        return pos

    def _pattern_ids(self, offs: np.ndarray) -> np.ndarray:
        """Index-pattern id per row of (n, 6) vertex offsets (block samples, from the anchor).
        The rows are told apart by one int64 key (the offsets as base-M digits, in [0, M)), so
        the distinct rows come out in the same (lexicographic) order as ``np.unique(axis=0)``
        gives, at a fraction of its cost: it sorts rows as structured records, 0.1 s for the
        131 072 patches of a full-resolution 4097² front (what a GPU draw waited on)."""
        uniq, inv = _distinct_rows(offs, self.pool.M)
        ids = np.empty(len(uniq), np.int64)
        changed = False
        for i, row in enumerate(map(tuple, uniq.tolist())):
            pid = self._patterns.get(row)
            if pid is None:
                tri = refine_uniform(*[np.array([v]) for v in row], 2 * self.k)  # (4^k, 3, 2) (x, y)
                tri = _facing_up(tri)
                idx = (tri[..., 1] * self.pool.M + tri[..., 0]).astype(np.uint32).ravel()
                pid = self._patterns[row] = len(self._pattern_data)
                self._pattern_data.append(idx)
                changed = True
            ids[i] = pid
        if changed or self.vao is None:
            self._rebuild()
        return ids[inv.ravel()]

    def _rebuild(self) -> None:
        if self._ibo is not None:
            self._ibo.release()
            self.vao.release()
            self._gvao.release()
        data = self._pattern_data + self._merged_data
        self._ibo = self.ctx.buffer(np.concatenate(data).tobytes() if data else np.zeros(3, np.uint32).tobytes())
        sizes = np.array([len(d) for d in self._merged_data], np.int64)
        self._merged_first = len(self._pattern_data) * 3 * self.tris_per_patch + np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        attrs = [(self.pool.vbo, "f", "in_h"), (self.pool.inst, "4i/i", "in_slot")]
        self.vao = self.ctx.vertex_array(self.programs.forward, attrs, index_buffer=self._ibo, index_element_size=4)
        self._gvao = self.ctx.vertex_array(self.programs.gbuffer, attrs, index_buffer=self._ibo, index_element_size=4)

    def _placement(self, front):
        """Per patch: its block's GL slot, index-pattern id, and its anchor's (row, col) inside
        the block (in the block's samples)."""
        M = self.pool.M
        slots = lookup_blocks(self.pool.slot_of, front.level, front.bi, front.bj)
        if (slots < 0).any():
            raise RuntimeError("a patch's block is not resident in the GL pool (the LOD must only select resident blocks)")
        lv = front.level.astype(np.int64)  # the sample step is 2**level: divisions of these non-negative offsets are shifts
        minx = np.minimum(np.minimum(front.ax, front.lx), front.rx)
        miny = np.minimum(np.minimum(front.ay, front.ly), front.ry)
        offs = np.empty((len(lv), 6), np.int64)
        for j, (v, m) in enumerate(((front.ax, minx), (front.ay, miny), (front.lx, minx), (front.ly, miny), (front.rx, minx), (front.ry, miny))):
            np.subtract(v, m, out=offs[:, j])
        offs >>= lv[:, None]
        pids = self._pattern_ids(offs)
        return slots, pids, (miny - (front.bi * (M - 1) << lv)) >> lv, (minx - (front.bj * (M - 1) << lv)) >> lv

    def front_triangles(self, front, cols: int, chunk: int = 8192) -> np.ndarray:
        """(T, 3) uint32 indices into the row-major finest grid (``cols`` samples per row) of
        the triangles :meth:`draw` draws for ``front``, in its order (baselines that draw the
        same triangles as one plain mesh)."""
        M = self.pool.M
        _, pids, row, col = self._placement(front)
        pat = np.stack(self._pattern_data).astype(np.int64)
        step = 2 ** front.level.astype(np.int64)
        oy, ox = front.bi * (M - 1) * step, front.bj * (M - 1) * step
        out = np.empty((len(front) * self.tris_per_patch * 3,), np.uint32)
        per = 3 * self.tris_per_patch
        for a in range(0, len(front), chunk):
            b = min(a + chunk, len(front))
            local = pat[pids[a:b]] + (row[a:b] * M + col[a:b])[:, None]
            r, c = local // M, local % M
            g = (oy[a:b, None] + r * step[a:b, None]) * cols + ox[a:b, None] + c * step[a:b, None]
            out[a * per:b * per] = g.ravel()
        return out.reshape(-1, 3)

    def draw(self, front, mvp: np.ndarray, tint=(0.0, 0.0, 0.0, 0.0), eye=(0.0, 0.0, 0.0)) -> int:
        """Draw every patch of ``front`` (all blocks must be resident); returns triangles. The sky
        behind is painted on the final image (:func:`massview.render.colormaps.paint_sky`)."""
        n = len(front)
        if n == 0:
            return 0
        cmds = self._commands(front, eye if self.sort else None)
        data = cmds.tobytes()
        if self._indirect is None or self._indirect.size < len(data):
            if self._indirect is not None:
                self._indirect.release()
            self._indirect = self.ctx.buffer(reserve=max(len(data), 1 << 16) * 2)
        self._indirect.write(data)
        self._uniform("u_mvp", np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        self._uniform("u_tint", tuple(tint))
        self._uniform("u_eye", tuple(float(v) for v in eye))
        self._uniform("u_haze_from", self.haze_from(eye))
        self.pool.shade.use(0)
        self.pool.ortho.use(1)
        self._pages.use(2)
        self._ramp.use(3)
        if self._cull(eye):
            self.ctx.enable(moderngl.CULL_FACE)
            self.ctx.cull_face, self.ctx.front_face = "back", "ccw"
        self.used_deferred = self._use_deferred(n * self.tris_per_patch)
        if self.used_deferred:
            self._draw_deferred(len(cmds))
        else:
            self.vao.render_indirect(self._indirect, mode=moderngl.TRIANGLES, count=len(cmds))
        self.ctx.disable(moderngl.CULL_FACE)
        self.draws = len(cmds)
        return n * self.tris_per_patch

    def _use_deferred(self, triangles: int) -> bool:
        if self.deferred is not None:
            return bool(self.deferred)
        fbo = self.ctx.fbo
        w, h = fbo.scissor[2:]  # the viewport when no scissor is set
        return triangles > DEFERRED_ABOVE * max(w * h, 1)

    def _cull(self, eye) -> bool:
        """Whether back faces can be culled without changing the image: the eye is above the
        highest sample (``peak``, exaggerated as drawn) and inside the terrain's footprint. A ray
        from there crosses the height field first from above, i.e. at a triangle facing up
        (:func:`_facing_up`); downward-facing triangles only ever lie behind it. Culling them
        saves their setup, binning and rasterization (a third to a half of a low flyover's)."""
        z = self.base + self.shading.exaggeration * (self.peak - self.base)
        return bool(eye[2] > z and 0.0 <= eye[0] <= self._footprint[0] and -self._footprint[1] <= eye[1] <= 0.0)

    def _commands(self, front, eye=None) -> np.ndarray:
        """(draws, 5) uint32 ``DrawElementsIndirectCommand`` rows for ``front``: one per patch in
        front order, then one per block the front covers whole at its level (all its
        2(M−1)²/4^k patches: e.g. every block at full resolution), drawn by one merged pattern.
        llvmpipe's per-draw cost (state, buffer mapping, a pipeline flush per draw) is then paid
        per block instead of per patch. With ``eye`` (world x, y, z) the rows are reordered
        front to back (:func:`_front_to_back`)."""
        M, tpp = self.pool.M, self.tris_per_patch
        slots, pids, row, col = self._placement(front)
        base = (row * M + col).astype(np.int64)
        full = 2 * (M - 1) ** 2 // tpp
        whole = np.bincount(slots)[slots] == full if self.merge else np.zeros(len(front), bool)
        part = ~whole
        cmds = np.empty((int(part.sum()), 5), np.uint32)
        cmds[:, 0] = 3 * tpp
        cmds[:, 1] = 1
        cmds[:, 2] = pids[part] * 3 * tpp
        cmds[:, 3] = slots[part] * M * M + base[part]
        cmds[:, 4] = slots[part]
        if whole.any():
            order = _stable_order(slots[whole])  # the whole blocks' patches, block by block
            cmds = np.concatenate([cmds, self._block_commands(slots[whole], pids[whole], base[whole], full, order)])
        if eye is None:
            return cmds
        d = self._distance2(front, eye)
        if whole.any():  # a whole block: its nearest patch (the rows _block_commands made, in its slot order)
            d = np.concatenate([d[part], d[whole][order].reshape(-1, full).min(1)])
        return cmds[_front_to_back(d)]

    def _distance2(self, front, eye) -> np.ndarray:
        """Squared horizontal world distance from ``eye`` to each patch's centroid (x = col·dx,
        y = −row·dy)."""
        dx, dy = self._spacing
        cx = (front.ax + front.lx + front.rx).astype(np.float64) * (dx / 3.0) - float(eye[0])
        cy = (front.ay + front.ly + front.ry).astype(np.float64) * (-dy / 3.0) - float(eye[1])
        return cx * cx + cy * cy

    def _block_commands(self, slots, pids, base, full: int, order=None) -> np.ndarray:
        """One command per whole block; its merged pattern (the block's patches sorted by
        (pattern, anchor)) is made once per distinct patch set (a few: the bintree's split
        directions) and kept in the index buffer after the patch patterns."""
        M, per = self.pool.M, 3 * self.tris_per_patch
        order = _stable_order(slots) if order is None else order
        keys = np.sort((pids[order] * M * M + base[order]).reshape(-1, full), axis=1)
        bslots = slots[order][::full]
        rows = [k.tobytes() for k in keys]  # a dict of the rows' bytes, not np.unique(axis=0): see _pattern_ids
        distinct = dict.fromkeys(rows)
        if len(self._merged) + len(distinct) > 64:  # bound the index buffer: start over
            self._merged.clear()
            self._merged_data.clear()
        new = [b for b in distinct if b not in self._merged]
        if new:  # ids in the rows' lexicographic order, as np.unique(axis=0) gave them
            arr = np.frombuffer(b"".join(new), keys.dtype).reshape(len(new), full)
            for i in np.lexsort(arr.T[::-1]):
                pat, anchor = np.divmod(arr[i], M * M)
                idx = (np.stack([self._pattern_data[q] for q in pat]).astype(np.int64) + anchor[:, None]).astype(np.uint32)
                self._merged[new[i]] = len(self._merged_data)
                self._merged_data.append(idx.ravel())
            self._rebuild()
        cmds = np.empty((len(bslots), 5), np.uint32)
        cmds[:, 0] = full * per
        cmds[:, 1] = 1
        cmds[:, 2] = self._merged_first[np.fromiter((self._merged[b] for b in rows), np.int64, len(rows))]
        cmds[:, 3] = bslots * M * M
        cmds[:, 4] = bslots
        return cmds

    def _draw_deferred(self, n: int) -> None:
        """Pass 1 into the bound target's G-buffer (its depth test), pass 2 shades the pixels
        pass 1 wrote into the target's colour (:mod:`.terrain_gbuffer`): a far-plane triangle
        with depth test GREATER and no depth writes, so pixels no terrain covers (depth 1.0, the
        sky) skip the shading shader; those pass 1 did not write in this draw are discarded."""
        ctx = self.ctx
        target = ctx.fbo
        gfbo = self._gbuffers.begin(target)
        self._gvao.render_indirect(self._indirect, mode=moderngl.TRIANGLES, count=n)
        target.use()
        for unit, tex in enumerate(self._gbuffers.textures(gfbo), start=4):
            tex.use(unit)
        ctx.disable(moderngl.CULL_FACE)
        ctx.depth_func = ">"  # the far-plane triangle passes where pass 1 (or an earlier draw) left depth < 1: not on sky
        target.depth_mask = False
        target.use()
        self._shade_vao.render(moderngl.TRIANGLES, vertices=3)
        target.depth_mask = True
        target.use()
        ctx.depth_func = "<"  # massview's terrain depth test (render/framebuffer.py)

    def release(self) -> None:
        self._gbuffers.release()
        for o in (self.vao, self._gvao, self._ibo, self._indirect, self._shade_vao, self._pages, self._ramp):
            if o is not None:
                o.release()
        self.programs.release()
