"""The massive-model client's three-level geometry cache (Revanth & Narayanan 2012, §3.8).

GPU buffers ← RAM ← disk, least recently used out at both upper levels, budgets in bytes:

* **GPU**: a :class:`~massview.render.scene.MeshPool` (one GL buffer of ``--gpu-mb`` bytes,
  first-fit, LRU eviction that spares the meshes of the current frame);
* **RAM**: a :class:`~massview.data.cache.BlockCache` of packed meshes (``--cache-mb``; the
  paper's ramdisk), loading from
* **disk**: the scene store (``store.get_mesh(geometry, level)``, packed by
  :func:`~massview.render.scene.pack_mesh`).

:meth:`GeometryCache.ensure` makes a frame's meshes resident on the GPU before it is drawn
(the paper's "load geometry to render"): meshes already on the GPU are reused (a static
camera uploads nothing on its second frame), the others come from RAM, and RAM misses are
all requested at once (the cache's worker threads read them in parallel) and awaited. The
frame waits for its geometry, so what is drawn is exactly the visible list. With
``wait=False`` (``--loading async``) only what RAM already holds is uploaded; the rest is
requested from the workers and left loading (``deferred``): the caller draws what is resident.
Counters per call: hits and loads per level, bytes uploaded and read from disk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError
from ..data.cache import BlockCache
from .scene import UNIT, MeshPool, pack_mesh

__all__ = ["CacheCounts", "GeometryCache", "packed_loader"]


@dataclass(frozen=True)
class CacheCounts:
    """One ``ensure`` call: meshes found on the GPU, found in RAM, read from disk; bytes
    uploaded to the GPU and read from disk; evictions at both levels; meshes left loading in
    the background (``wait=False`` only)."""

    gpu_hits: int
    ram_hits: int
    disk_loads: int
    bytes_uploaded: int
    bytes_from_disk: int
    gpu_evictions: int
    ram_evictions: int
    deferred: int = 0

    def to_counters(self, prefix: str = "") -> dict:
        return {prefix + k: v for k, v in self.__dict__.items()}


def packed_loader(store):
    """The RAM level's loader: ``(geometry, level) -> packed uint8 mesh`` read from ``store``."""

    def load(key):
        m = store.get_mesh(int(key[0]), int(key[1]))
        return pack_mesh(m.positions, m.normals, m.colors, m.indices)

    return load


class GeometryCache:
    """GPU pool over a RAM cache over a store (see the module doc)."""

    def __init__(self, pool: MeshPool, ram: BlockCache, timeout: float = 120.0):
        self.pool, self.ram, self.timeout = pool, ram, timeout

    def ensure(self, keys, wait: bool = True, priority: float = 1.0) -> CacheCounts:
        """Make every ``(geometry, level)`` of ``keys`` resident in the GPU pool; with
        ``wait=False`` only those in RAM, requesting the others at ``priority`` (higher first)."""
        keys = list(dict.fromkeys((int(g), int(lv)) for g, lv in keys))
        keep = set(keys)
        pool, ram = self.pool, self.ram
        gpu_ev0, ram_ev0 = pool.evictions, ram.counters["evictions"]
        loads0, disk0 = ram.counters["loads"], ram.counters["bytes_loaded"]
        missing = [k for k in keys if not pool.resident[k]]
        pool.touch(k for k in keys if pool.resident[k])
        held = {k: ram.get(k) for k in missing if ram.contains(k)}  # hold them: loads below may evict
        held = {k: v for k, v in held.items() if v is not None}
        for k in missing:
            if k not in held:
                ram.request(k, float("inf") if wait else priority)  # all at once: the workers read them in parallel
        uploaded = 0
        for k in missing:
            packed = held.get(k)
            if packed is None and not wait:
                continue
            if packed is None:
                packed = ram.get_blocking(k, self.timeout)
            if not pool.upload(k, packed, keep):
                raise ConfigError(f"the meshes of one frame do not fit the GPU budget ({pool.budget} bytes, "
                                  f"{len(keys)} meshes); raise --gpu-mb")
            uploaded += int(packed.nbytes) - 16
        return CacheCounts(len(keys) - len(missing), len(held), ram.counters["loads"] - loads0, uploaded,
                           ram.counters["bytes_loaded"] - disk0, pool.evictions - gpu_ev0, ram.counters["evictions"] - ram_ev0,
                           0 if wait else len(missing) - len(held))

    def stored_bytes(self, key) -> bytes:
        """The bytes the GPU pool holds for ``key`` (vertices then indices), read back."""
        start, _ = self.pool.slots[key]
        vbytes = int(self.pool.first_index[key]) * 4 - start * UNIT
        return self.pool.buffer.read(size=vbytes + int(self.pool.index_count[key]) * 4, offset=start * UNIT)

    @property
    def gpu_bytes(self) -> int:
        return self.pool.used_bytes

    @property
    def ram_bytes(self) -> int:
        return self.ram.resident_bytes

    @staticmethod
    def ram_budget(total_object_bytes: int, clients: int) -> int:
        """The paper's §4 default RAM budget: the scene's object bytes ÷ clients."""
        return max(1, int(np.ceil(total_object_bytes / max(clients, 1))))
