"""Drawing scene objects from a byte-budget GL pool of meshes (one per geometry and level).

* :func:`pack_mesh` turns a store mesh (float32 positions and normals, RGBA8 unlit colours,
  uint32 triangle indices) into one uint8 array — a 16-byte header (vertex and index counts),
  interleaved 24-byte vertices (float32 position, float16 normal, RGBA8 colour) and the
  indices — the unit the RAM cache holds and the pool uploads.
* :class:`MeshPool` is one GL buffer of ``budget`` bytes, used as vertex *and* index buffer,
  managed by a first-fit allocator in 24-byte units with coalescing free lists. Meshes are
  evicted least recently used (never one drawn this frame) until a new one fits, so the
  resident bytes never exceed the budget. ``resident`` is a (geometries, levels) bool grid.
* :class:`SceneRenderer` draws any list of (object, level) with one
  ``glMultiDrawElementsIndirect``: per draw ``baseVertex`` and ``firstIndex`` locate the mesh
  in the pool and ``baseInstance`` its row in a per-frame instance buffer holding the
  object's camera-relative model matrix (float64 on the CPU, so large scenes keep precision)
  and its normal matrix; fragments are lit with the normals (two-sided Lambert + ambient).
"""

from __future__ import annotations

import bisect
from collections import OrderedDict

import moderngl
import numpy as np

from ..core.errors import ConfigError
from .context import load_shader
from .meshes import _LIGHT

__all__ = ["VERTEX_DTYPE", "pack_mesh", "MeshPool", "SceneRenderer"]

VERTEX_DTYPE = np.dtype([("p", "<f4", 3), ("n", "<f2", 3), ("pad", "<u2"), ("c", "u1", 4)])
UNIT = VERTEX_DTYPE.itemsize  # 24 bytes: the pool's allocation unit
_HEADER = 16
_INSTANCE = np.dtype([("m", "<f4", 16), ("n", "<f4", 9)])  # model (column-major), normal matrix


def pack_mesh(positions: np.ndarray, normals: np.ndarray, colors: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(bytes,) uint8: header (int64 vertex count, int64 index count), vertices, indices."""
    v = np.empty(len(positions), VERTEX_DTYPE)
    v["p"] = positions
    v["n"] = normals
    v["pad"] = 0
    v["c"] = colors
    idx = np.ascontiguousarray(indices, np.uint32).ravel()
    head = np.array([len(v), len(idx)], np.int64)
    return np.concatenate([head.view(np.uint8), v.view(np.uint8), idx.view(np.uint8)])


def unpack_counts(packed: np.ndarray) -> tuple[int, int]:
    nv, ni = packed[:_HEADER].view(np.int64)
    return int(nv), int(ni)


class MeshPool:
    """GL buffer of ``budget_bytes`` holding meshes keyed by (geometry, level)."""

    def __init__(self, ctx: moderngl.Context, geometries: int, levels: int, budget_bytes: int):
        self.units = int(budget_bytes // UNIT)
        if self.units < 1:
            raise ConfigError(f"GL pool budget {budget_bytes} bytes is too small; raise --gpu-mb")
        self.budget = self.units * UNIT
        self.buffer = ctx.buffer(reserve=self.budget)
        self._free_start = [0]  # sorted starts of free extents (units)
        self._free_size = [self.units]
        self.slots: OrderedDict[tuple[int, int], tuple[int, int]] = OrderedDict()  # key -> (start, units)
        self.resident = np.zeros((geometries, levels), bool)
        self.base_vertex = np.zeros((geometries, levels), np.int64)
        self.first_index = np.zeros((geometries, levels), np.int64)
        self.index_count = np.zeros((geometries, levels), np.int64)
        self.used_units = 0
        self.uploads = self.evictions = 0

    @property
    def used_bytes(self) -> int:
        return self.used_units * UNIT

    # -- allocator ----------------------------------------------------------------------
    def _alloc(self, units: int) -> int | None:
        for i, size in enumerate(self._free_size):
            if size >= units:
                start = self._free_start[i]
                if size == units:
                    del self._free_start[i], self._free_size[i]
                else:
                    self._free_start[i] += units
                    self._free_size[i] -= units
                return start
        return None

    def _release(self, start: int, units: int) -> None:
        i = bisect.bisect_left(self._free_start, start)
        self._free_start.insert(i, start)
        self._free_size.insert(i, units)
        if i + 1 < len(self._free_start) and start + units == self._free_start[i + 1]:  # merge right
            self._free_size[i] += self._free_size.pop(i + 1)
            self._free_start.pop(i + 1)
        if i > 0 and self._free_start[i - 1] + self._free_size[i - 1] == start:  # merge left
            self._free_size[i - 1] += self._free_size.pop(i)
            self._free_start.pop(i)

    def _evict(self, key) -> None:
        start, units = self.slots.pop(key)
        self._release(start, units)
        self.resident[key] = False
        self.used_units -= units
        self.evictions += 1

    # -- public -------------------------------------------------------------------------
    def upload(self, key: tuple[int, int], packed: np.ndarray, keep: set) -> bool:
        """Put a packed mesh in the pool, evicting least-recently-used meshes not in ``keep``
        until it fits; False when it cannot fit now."""
        if key in self.slots:
            self.slots.move_to_end(key)
            return True
        nv, ni = unpack_counts(packed)
        vbytes = nv * UNIT
        units = -(-(vbytes + ni * 4) // UNIT)
        if units > self.units:
            return False
        start = self._alloc(units)
        while start is None:
            victim = next((k for k in self.slots if k not in keep), None)
            if victim is None:
                return False
            self._evict(victim)
            start = self._alloc(units)
        body = packed[_HEADER:]
        self.buffer.write(body.tobytes(), offset=start * UNIT)
        self.slots[key] = (start, units)
        self.resident[key] = True
        self.base_vertex[key] = start
        self.first_index[key] = (start * UNIT + vbytes) // 4
        self.index_count[key] = ni
        self.used_units += units
        self.uploads += 1
        return True

    def touch(self, keys) -> None:
        for k in keys:
            if k in self.slots:
                self.slots.move_to_end(k)

    def release(self) -> None:
        self.buffer.release()


class SceneRenderer:
    def __init__(self, ctx: moderngl.Context, pool: MeshPool):
        self.ctx, self.pool = ctx, pool
        self.prog = ctx.program(vertex_shader=load_shader("scene.vert.glsl"), fragment_shader=load_shader("scene.frag.glsl"))
        self.prog["u_light"].value = tuple(_LIGHT)
        self._inst = ctx.buffer(reserve=_INSTANCE.itemsize * 1024)
        self._indirect = ctx.buffer(reserve=20 * 1024)
        self._vao = None
        self._bind()

    def _bind(self) -> None:
        if self._vao is not None:
            self._vao.release()
        self._vao = self.ctx.vertex_array(
            self.prog,
            [(self.pool.buffer, "3f 3f2 2x 4f1", "in_pos", "in_normal", "in_color"),
             (self._inst, "4f 4f 4f 4f 3f 3f 3f/i", "in_m0", "in_m1", "in_m2", "in_m3", "in_n0", "in_n1", "in_n2")],
            index_buffer=self.pool.buffer, index_element_size=4)

    def _reserve(self, n: int) -> None:
        if self._inst.size < n * _INSTANCE.itemsize or self._indirect.size < n * 20:
            self._inst.release()
            self._indirect.release()
            self._inst = self.ctx.buffer(reserve=n * 2 * _INSTANCE.itemsize)
            self._indirect = self.ctx.buffer(reserve=n * 2 * 20)
            self._bind()

    def draw(self, geometry: np.ndarray, level: np.ndarray, model: np.ndarray, normal: np.ndarray,
             eye: np.ndarray, view_rot_proj: np.ndarray, tint=(0.0, 0.0, 0.0, 0.0)) -> int:
        """Draw objects in the given order: ``geometry``/``level`` (k,) int (resident in the
        pool), ``model`` (k, 4, 4) float64 world matrices, ``normal`` (k, 3, 3) normal
        matrices, ``eye`` the camera position and ``view_rot_proj`` the float64 4x4
        projection · view with the eye at the origin. Returns triangles submitted."""
        k = len(geometry)
        if k == 0:
            return 0
        p = self.pool
        if not p.resident[geometry, level].all():
            raise RuntimeError("an object's mesh is not resident in the GL pool (the level choice must only pick resident meshes)")
        count = p.index_count[geometry, level]
        cmds = np.empty((k, 5), np.uint32)
        cmds[:, 0] = count
        cmds[:, 1] = 1
        cmds[:, 2] = p.first_index[geometry, level]
        cmds[:, 3] = p.base_vertex[geometry, level]
        cmds[:, 4] = np.arange(k)
        rel = np.array(model, np.float64)
        rel[:, :3, 3] -= eye  # camera-relative: float32 keeps precision far from the origin
        inst = np.empty(k, _INSTANCE)
        inst["m"] = rel.transpose(0, 2, 1).reshape(k, 16)
        inst["n"] = np.asarray(normal).transpose(0, 2, 1).reshape(k, 9)
        self._reserve(k)
        self._inst.write(inst.tobytes())
        self._indirect.write(cmds.tobytes())
        self.prog["u_vp"].write(np.ascontiguousarray(view_rot_proj.T, dtype="f4").tobytes())
        self.prog["u_tint"].value = tuple(tint)
        self._vao.render_indirect(self._indirect, mode=moderngl.TRIANGLES, count=k)
        return int(count.sum() // 3)

    def release(self) -> None:
        for o in (self._vao, self._inst, self._indirect, self.prog):
            o.release()
