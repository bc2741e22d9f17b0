"""The client's three-level geometry cache (GPU pool ← RAM ← store), §3.8: byte budgets hold,
the GPU holds the stored bytes, a static camera uploads nothing on its second frame."""

from __future__ import annotations

import numpy as np
import pytest

from massview.core.errors import ConfigError
from massview.data.cache import BlockCache
from massview.render.geometry_cache import GeometryCache, packed_loader
from massview.render.scene import MeshPool

from scene_helpers import MemoryScene


@pytest.fixture(scope="module")
def scene():
    return MemoryScene(side=6, seed=2, lmax=3)


def _cache(ctx, scene, gpu_bytes, ram_bytes):
    load = packed_loader(scene)
    sizes = {k: load(k).nbytes for k in scene.meshes}
    pool = MeshPool(ctx, len(scene.skeleton.radius), 3, gpu_bytes)
    return GeometryCache(pool, BlockCache(load, ram_bytes, workers=2)), load, sizes


def test_budgets_hold_and_the_gpu_holds_the_stored_bytes(ctx, scene):
    cache, load, sizes = _cache(ctx, scene, 400_000, 300_000)
    rng = np.random.default_rng(0)
    keys = sorted(scene.meshes)
    try:
        for _ in range(25):
            frame = [keys[i] for i in rng.choice(len(keys), 6, replace=False)]
            c = cache.ensure(frame)
            assert c.gpu_hits + c.ram_hits + c.disk_loads == len(frame)  # every mesh came from one level
            assert cache.gpu_bytes <= cache.pool.budget and cache.ram_bytes <= cache.ram.budget
            for k in frame:
                assert cache.pool.resident[k]
                assert cache.stored_bytes(k) == load(k)[16:].tobytes()
        s = cache.ram.stats()
        assert s["evictions"] > 0 and cache.pool.evictions > 0  # both levels had to evict
    finally:
        cache.ram.close()


def test_static_camera_uploads_nothing_on_its_second_frame(ctx, scene):
    cache, _, sizes = _cache(ctx, scene, 1 << 20, 1 << 20)
    frame = [(i, i % 3) for i in range(0, 36, 3)]
    try:
        first = cache.ensure(frame)
        assert first.disk_loads == len(frame) and first.gpu_hits == 0
        assert first.bytes_uploaded == sum(sizes[k] - 16 for k in frame)
        assert first.bytes_from_disk == sum(sizes[k] for k in frame)
        second = cache.ensure(frame)
        assert second.bytes_uploaded == 0 and second.disk_loads == 0 and second.gpu_hits == len(frame)
    finally:
        cache.ram.close()


def test_three_levels_gpu_miss_ram_hit_then_disk(ctx, scene):
    a = [(i, 0) for i in range(0, 4)]
    b = [(i, 0) for i in range(4, 8)]
    load = packed_loader(scene)
    need = max(sum(load(k).nbytes for k in a), sum(load(k).nbytes for k in b))
    cache, _, _ = _cache(ctx, scene, need + 4096, 10 << 20)  # the GPU holds one frame, RAM both
    try:
        cache.ensure(a)
        cache.ensure(b)  # evicts a from the GPU
        back = cache.ensure(a)
        assert back.gpu_hits == 0 and back.ram_hits == len(a) and back.disk_loads == 0 and back.bytes_uploaded > 0
    finally:
        cache.ram.close()
    small, _, _ = _cache(ctx, scene, need + 4096, need + 4096)  # RAM holds one frame too
    try:
        small.ensure(a)
        small.ensure(b)
        back = small.ensure(a)
        assert back.ram_hits == 0 and back.disk_loads == len(a)
    finally:
        small.ram.close()


def test_a_frame_larger_than_the_gpu_budget_is_a_clear_error(ctx, scene):
    cache, _, _ = _cache(ctx, scene, 40_000, 10 << 20)
    try:
        with pytest.raises(ConfigError, match="--gpu-mb"):
            cache.ensure([(i, 0) for i in range(36)])
    finally:
        cache.ram.close()
