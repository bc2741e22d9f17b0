"""Drawing terrain K-patches (RASTeR's rendering side).

* :func:`pack_block` turns a block of heights (+ colour) into interleaved vertices:
  float32 height, float16 normal x/y, RGBA8 colour — 12 bytes per sample.
* :class:`BlockPool` keeps resident blocks once each in one GL vertex buffer of fixed slots
  (its byte budget / (M²·12)), evicting least-recently used slots.
* K-patch index patterns are static: one per patch shape (orientation × sample step),
  generated once by uniform refinement and shared by all blocks; a patch is drawn with
  ``baseVertex`` = its block slot and anchor sample, ``baseInstance`` = the slot.
* :meth:`TerrainRenderer.draw` issues the whole front as one ``glMultiDrawElementsIndirect``.
"""

from __future__ import annotations

from collections import OrderedDict

import moderngl
import numpy as np

from ..core.errors import ConfigError
from ..lod.kpatch import lookup_blocks, refine_uniform
from .context import load_shader

__all__ = ["VERTEX_BYTES", "pack_block", "BlockPool", "TerrainRenderer", "PlainMeshRenderer"]

VERTEX_DTYPE = np.dtype([("h", "<f4"), ("n", "<f2", 2), ("c", "u1", 4)])
VERTEX_BYTES = VERTEX_DTYPE.itemsize
_LIGHT = np.array([-0.45, 0.35, 0.82])
_LIGHT = (_LIGHT / np.linalg.norm(_LIGHT)).astype("f4")


def pack_block(h: np.ndarray, color: np.ndarray | None, dx: float, dy: float, vscale: float) -> np.ndarray:
    """(M·M,) interleaved vertices of a block; ``dx, dy`` are world metres between its samples.
    Normals from central differences of the scaled heights (world frame: y = −row)."""
    gy, gx = np.gradient(h.astype(np.float32) * vscale, dy, dx)
    nx, ny = -gx, gy  # d/dy_world = −d/drow
    inv = 1.0 / np.sqrt(nx * nx + ny * ny + 1.0)
    out = np.empty(h.size, VERTEX_DTYPE)
    out["h"] = h.ravel()
    out["n"][:, 0] = (nx * inv).ravel()
    out["n"][:, 1] = (ny * inv).ravel()
    if color is None:
        out["c"] = (180, 170, 150, 255)
    else:
        out["c"][:, :3] = color.reshape(-1, 3)
        out["c"][:, 3] = 255
    return out


def _terrain_program(ctx: moderngl.Context, row_length: int, spacing, vscale: float, rows: int, cols: int):
    """The terrain shader program with its constant uniforms (``row_length`` = samples per
    vertex-grid row: M for block slots, the grid width for a plain mesh)."""
    prog = ctx.program(vertex_shader=load_shader("terrain.vert.glsl"), fragment_shader=load_shader("terrain.frag.glsl"))
    prog["u_M"].value = row_length
    prog["u_scale"].value = (float(spacing[0]), float(spacing[1]), float(vscale))
    prog["u_light"].value = tuple(_LIGHT)
    prog["u_extent"].value = (float(cols - 1), float(rows - 1))
    return prog


class BlockPool:
    """Fixed GL slots for resident blocks, LRU; ``resident[level]`` is a (nb, nb) bool grid."""

    def __init__(self, ctx: moderngl.Context, M: int, levels: int, top: int, budget_bytes: int):
        self.M = M
        self.slot_bytes = M * M * VERTEX_BYTES
        self.capacity = int(budget_bytes // self.slot_bytes)
        if self.capacity < 1:
            raise ConfigError(f"GL budget {budget_bytes} bytes is smaller than one block ({self.slot_bytes} bytes); raise --gpu-mb")
        self.vbo = ctx.buffer(reserve=self.capacity * self.slot_bytes)
        self.inst = ctx.buffer(reserve=self.capacity * 16)
        self.slots: OrderedDict[tuple, int] = OrderedDict()
        self.free = list(range(self.capacity - 1, -1, -1))
        self.resident = [np.zeros((2 ** (top - lv), 2 ** (top - lv)), bool) for lv in range(levels)]
        self.slot_of = [np.full((2 ** (top - lv), 2 ** (top - lv)), -1, np.int64) for lv in range(levels)]
        self.uploads = 0

    @property
    def gpu_bytes(self) -> int:
        return self.capacity * (self.slot_bytes + 16)

    def upload(self, key: tuple[int, int, int], vertices: np.ndarray, origin: tuple[int, int], step: int, keep: set) -> bool:
        """Put a block in a slot (evicting the LRU block not in ``keep``); False when full."""
        if key in self.slots:
            self.slots.move_to_end(key)
            return True
        if not self.free:
            victim = next((k for k in self.slots if k not in keep), None)
            if victim is None:
                return False
            s = self.slots.pop(victim)
            self.resident[victim[0]][victim[1], victim[2]] = False
            self.slot_of[victim[0]][victim[1], victim[2]] = -1
            self.free.append(s)
        s = self.free.pop()
        self.vbo.write(vertices.tobytes(), offset=s * self.slot_bytes)
        self.inst.write(np.array([origin[1], origin[0], step, s], np.int32).tobytes(), offset=s * 16)
        self.slots[key] = s
        self.resident[key[0]][key[1], key[2]] = True
        self.slot_of[key[0]][key[1], key[2]] = s
        self.uploads += 1
        return True

    def touch(self, keys) -> None:
        for k in keys:
            if k in self.slots:
                self.slots.move_to_end(k)

    def release(self) -> None:
        self.vbo.release()
        self.inst.release()


class TerrainRenderer:
    def __init__(self, ctx: moderngl.Context, pool: BlockPool, k: int, spacing, vscale: float, extent: tuple[int, int]):
        self.ctx, self.pool, self.k = ctx, pool, k
        self.prog = _terrain_program(ctx, pool.M, spacing, vscale, extent[0], extent[1])
        self._patterns: dict[tuple, int] = {}
        self._pattern_data: list[np.ndarray] = []
        self._ibo = None
        self.vao = None
        self._indirect = None
        self.tris_per_patch = 4**k

    def _pattern_ids(self, offs: np.ndarray) -> np.ndarray:
        """Index-pattern id per row of (n, 6) vertex offsets (block samples, from the anchor)."""
        uniq, inv = np.unique(offs, axis=0, return_inverse=True)
        ids = np.empty(len(uniq), np.int64)
        changed = False
        for i, row in enumerate(map(tuple, uniq.tolist())):
            pid = self._patterns.get(row)
            if pid is None:
                tri = refine_uniform(*[np.array([v]) for v in row], 2 * self.k)  # (4^k, 3, 2) (x, y)
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
        self._ibo = self.ctx.buffer(np.concatenate(self._pattern_data).tobytes() if self._pattern_data else np.zeros(3, np.uint32).tobytes())
        self.vao = self.ctx.vertex_array(
            self.prog,
            [(self.pool.vbo, "f 2f2 4f1", "in_h", "in_n", "in_color"), (self.pool.inst, "4i/i", "in_slot")],
            index_buffer=self._ibo, index_element_size=4)

    def draw(self, front, mvp: np.ndarray, tint=(0.0, 0.0, 0.0, 0.0)) -> int:
        """Draw every patch of ``front`` (all blocks must be resident); returns triangles."""
        n = len(front)
        if n == 0:
            return 0
        M = self.pool.M

        slots = lookup_blocks(self.pool.slot_of, front.level, front.bi, front.bj)
        if (slots < 0).any():
            raise RuntimeError("a patch's block is not resident in the GL pool (the LOD must only select resident blocks)")
        step = 2 ** front.level.astype(np.int64)
        span = (M - 1) * step
        minx = np.minimum(np.minimum(front.ax, front.lx), front.rx)
        miny = np.minimum(np.minimum(front.ay, front.ly), front.ry)
        offs = np.stack([front.ax - minx, front.ay - miny, front.lx - minx, front.ly - miny, front.rx - minx, front.ry - miny], 1) // step[:, None]
        pids = self._pattern_ids(offs)
        col = (minx - front.bj * span) // step
        row = (miny - front.bi * span) // step
        per = 3 * self.tris_per_patch
        cmds = np.empty((n, 5), np.uint32)
        cmds[:, 0] = per
        cmds[:, 1] = 1
        cmds[:, 2] = pids * per
        cmds[:, 3] = slots * M * M + row * M + col
        cmds[:, 4] = slots
        data = cmds.tobytes()
        if self._indirect is None or self._indirect.size < len(data):
            if self._indirect is not None:
                self._indirect.release()
            self._indirect = self.ctx.buffer(reserve=max(len(data), 1 << 16) * 2)
        self._indirect.write(data)
        self.prog["u_mvp"].write(np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        self.prog["u_tint"].value = tuple(tint)
        self.vao.render_indirect(self._indirect, mode=moderngl.TRIANGLES, count=n)
        return n * self.tris_per_patch

    def release(self) -> None:
        for o in (self.vao, self._ibo, self._indirect, self.prog):
            if o is not None:
                o.release()


class PlainMeshRenderer:
    """The baseline without LOD: the finest level as one static indexed mesh (what a user
    would draw without a terrain system). Shares the terrain shaders and block packing."""

    def __init__(self, ctx: moderngl.Context, heights: np.ndarray, color: np.ndarray | None, spacing, vscale: float):
        rows, cols = heights.shape
        self.ctx = ctx
        self.triangles = 2 * (rows - 1) * (cols - 1)
        verts = pack_block(heights, color, spacing[0], spacing[1], vscale)
        self.vbo = ctx.buffer(verts.tobytes())
        self.inst = ctx.buffer(np.array([0, 0, 1, 0], np.int32).tobytes())
        r, c = np.meshgrid(np.arange(rows - 1, dtype=np.uint32), np.arange(cols - 1, dtype=np.uint32), indexing="ij")
        a = (r * cols + c).ravel()
        idx = np.stack([a, a + cols, a + 1, a + 1, a + cols, a + cols + 1], 1).ravel()
        self.ibo = ctx.buffer(idx.tobytes())
        self.prog = _terrain_program(ctx, cols, spacing, vscale, rows, cols)  # one grid row = one "block" row
        self.vao = ctx.vertex_array(self.prog, [(self.vbo, "f 2f2 4f1", "in_h", "in_n", "in_color"), (self.inst, "4i/i", "in_slot")],
                                    index_buffer=self.ibo, index_element_size=4)

    def draw(self, mvp: np.ndarray) -> int:
        self.prog["u_mvp"].write(np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        self.prog["u_tint"].value = (0.0, 0.0, 0.0, 0.0)
        self.vao.render(moderngl.TRIANGLES)
        return self.triangles

    def release(self) -> None:
        for o in (self.vao, self.ibo, self.vbo, self.inst, self.prog):
            o.release()
