"""The GL block pool of the terrain renderer (RASTeR's resident blocks).

* :func:`pack_payload` packs a block for the pool: float32 heights (the vertices: position
  comes from the sample index), float16 shading maps, orthophoto colour if any.
* :class:`BlockPool` keeps resident blocks once each in fixed slots (its byte budget / slot
  bytes), evicting least-recently used slots: the heights in one GL vertex buffer, the block's
  shading maps (slopes + height, :mod:`massview.data.terrain.colors`) and orthophoto colour in
  one layer each of two texture arrays; a page table tells the fragment stage which blocks
  it may read.
"""

from __future__ import annotations

from collections import OrderedDict

import moderngl
import numpy as np

from ..core.errors import ConfigError

__all__ = ["pack_payload", "payload_bytes", "payload_parts", "layer_bytes", "BlockPool"]


def payload_bytes(M: int, ortho: bool) -> int:
    """The bytes of one block's :func:`pack_payload` array."""
    return M * M * (4 + 6 + (3 if ortho else 0))


def payload_parts(buf: np.ndarray, M: int, ortho: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(heights float32 (M, M), shading float16 (M, M, 3), colour uint8 (M, M, 3) or None):
    writable views of the uint8 payload ``buf`` (:func:`payload_bytes` long), to fill in place."""
    h, s = M * M * 4, M * M * 6
    return (buf[:h].view(np.float32).reshape(M, M), buf[h:h + s].view(np.float16).reshape(M, M, 3),
            buf[h + s:h + s + M * M * 3].reshape(M, M, 3) if ortho else None)


def pack_payload(heights: np.ndarray, shade: np.ndarray, ortho: np.ndarray | None) -> np.ndarray:
    """One uint8 array per block for the RAM cache and the GL pool: float32 (M, M) heights (the
    vertices), float16 (M, M, 3) shading maps, (M, M, 3) uint8 orthophoto colour if any (the
    layout :func:`payload_parts` views)."""
    M = heights.shape[0]
    out = np.empty(payload_bytes(M, ortho is not None), np.uint8)
    h, s, c = payload_parts(out, M, ortho is not None)
    h[...], s[...] = heights, shade
    if c is not None:
        c[...] = ortho
    return out


def layer_bytes(M: int, texel: int) -> int:
    """GL's bytes for an M × M texture-array layer of ``texel``-byte texels (RGB16F is stored as
    RGBA16F: 8; RGB8 as RGBA8: 4), rows padded to 64 bytes and 4 rows, as llvmpipe measured."""
    return -(-M // 4) * 4 * (-(-M * texel // 64) * 64)


def pool_sizes(M: int, ortho: bool) -> tuple[int, int]:
    """(bytes of one slot with its instance record, fixed bytes) of a :class:`BlockPool` of
    M² blocks: the slot's heights, shading layer (and colour layer), + 16; the fixed part is the
    one-layer orthophoto array drawn when the store has none."""
    return M * M * 4 + layer_bytes(M, 8) + (layer_bytes(M, 4) if ortho else 0) + 16, 0 if ortho else layer_bytes(M, 4)


def check_pool_budget(budget_bytes: int, M: int, ortho: bool) -> None:
    """ConfigError naming ``--gpu-mb`` where it cannot hold one block (what :class:`BlockPool`
    would refuse; also checked before any rank starts, :func:`massview.api.validate`)."""
    per_slot, fixed = pool_sizes(M, ortho)
    if budget_bytes - fixed < per_slot:
        need = fixed + per_slot
        raise ConfigError(f"--gpu-mb {budget_bytes / 2**20:g}: the GL pool needs at least {need / 2**20:.2f} MiB for one "
                          f"{M}² block ({need} bytes with its shading, colour and instance record); raise --gpu-mb")


class BlockPool:
    """Fixed GL slots for resident blocks, LRU; ``resident[level]`` is a (nb, nb) bool grid."""

    def __init__(self, ctx: moderngl.Context, M: int, levels: int, top: int, budget_bytes: int, ortho: bool = False):
        self.M, self.has_ortho = M, ortho
        self.vertex_bytes, self.shade_bytes = M * M * 4, M * M * 6
        per_slot, self._fixed = pool_sizes(M, ortho)  # (+ its instance record)
        self.slot_bytes = per_slot - 16
        check_pool_budget(budget_bytes, M, ortho)
        self.capacity = min(int((budget_bytes - self._fixed) // per_slot), int(ctx.info.get("GL_MAX_ARRAY_TEXTURE_LAYERS", 256)))
        self.vbo = ctx.buffer(reserve=self.capacity * self.vertex_bytes)
        self.inst = ctx.buffer(reserve=self.capacity * 16)
        self.shade = ctx.texture_array((M, M, self.capacity), 3, dtype="f2")
        self.ortho = ctx.texture_array((M, M, self.capacity if ortho else 1), 3, dtype="f1")
        for t in (self.shade, self.ortho):
            t.filter = (moderngl.LINEAR, moderngl.LINEAR)
            t.repeat_x = t.repeat_y = False
        self.slots: OrderedDict[tuple, int] = OrderedDict()
        self.free = list(range(self.capacity - 1, -1, -1))
        self.resident = [np.zeros((2 ** (top - lv), 2 ** (top - lv)), bool) for lv in range(levels)]
        self.slot_of = [np.full((2 ** (top - lv), 2 ** (top - lv)), -1, np.int64) for lv in range(levels)]
        self.uploads = 0

    @property
    def gpu_bytes(self) -> int:
        return self.capacity * (self.slot_bytes + 16) + self._fixed

    def upload(self, key: tuple[int, int, int], payload: np.ndarray, origin: tuple[int, int], step: int, keep: set) -> bool:
        """Put a block (a :func:`pack_payload` array) in a slot, evicting the LRU block not in
        ``keep``; False when full."""
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
        M, vb, sb = self.M, self.vertex_bytes, self.shade_bytes
        self.vbo.write(payload[:vb].tobytes(), offset=s * vb)
        self.shade.write(payload[vb:vb + sb].tobytes(), viewport=(0, 0, s, M, M, 1))
        if self.has_ortho:
            self.ortho.write(payload[vb + sb:].tobytes(), viewport=(0, 0, s, M, M, 1))
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

    def page_table(self, agreed: list[np.ndarray] | None = None) -> np.ndarray:
        """(Σ nb_l, nb_0) int32: the slot of every block whose residency every rank agrees on
        (``agreed`` grids; default: this pool's), else -1; level l starts at row Σ_{l'<l} nb_l'."""
        nb0 = self.slot_of[0].shape[0]
        out = np.full((sum(g.shape[0] for g in self.slot_of), nb0), -1, np.int32)
        r = 0
        for lv, slots in enumerate(self.slot_of):
            ok = (agreed[lv] if agreed is not None else self.resident[lv]) & (slots >= 0)
            n = slots.shape[0]
            out[r:r + n, :n] = np.where(ok, slots, -1)
            r += n
        return out

    def release(self) -> None:
        for o in (self.vbo, self.inst, self.shade, self.ortho):
            o.release()
