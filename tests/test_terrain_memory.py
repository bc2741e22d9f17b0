"""Terrain memory budgets are honest (issue 20): the GL block pool's budget bounds the memory GL
really takes for it (llvmpipe holds it in the process), the RAM cache holds no second copy of
what the pool holds, and the K-patch hierarchy's compact storage gives the eager float64
values bit for bit."""

import numpy as np
import pytest

import massview as mv
from massview.core.config import RenderConfig
from massview.data.cache import BlockCache
from massview.data.terrain import TerrainStore
from massview.lod.kpatch import Lazy, PatchHierarchy
from massview.render.context import create_context, renderer_string
from massview.render.terrain import BlockPool


def _rss_mib() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS:"))


def test_block_pool_budget_bounds_what_gl_holds():
    """Under llvmpipe the pool's textures and buffers are this process's memory: creating a
    64 MiB pool may not grow RSS by more than the bytes it counts (+ 4 MiB of GL objects).
    Counting the shading layer as 6 bytes a texel (RGB16F) grew it by 24 % more than counted."""
    ctx = create_context()
    if "llvmpipe" not in renderer_string(ctx):
        pytest.skip("GL memory is process memory only under llvmpipe")
    before = _rss_mib()
    pool = BlockPool(ctx, 257, 5, 4, 64 << 20)
    grown = _rss_mib() - before
    assert pool.gpu_bytes <= 64 << 20
    assert grown <= pool.gpu_bytes / 2**20 + 4, (grown, pool.gpu_bytes / 2**20)
    pool.release()


def test_cache_discard_takes_bytes_out_of_the_budget():
    cache = BlockCache(lambda k: np.zeros(100, np.uint8), 1000, workers=1)
    try:
        for k in range(3):
            cache.get_blocking(k)
        assert cache.resident_bytes == 300 and cache.peak_bytes == 300
        assert cache.discard(1) and not cache.discard(1) and not cache.contains(1)
        assert cache.resident_bytes == 200 and cache.stats()["discarded"] == 1 and cache.peak_bytes == 300
    finally:
        cache.close()


def test_ram_cache_holds_no_block_the_pool_holds(terrain_store):
    """After frames with complete loading, every block drawn is in the GL pool and the RAM cache
    stages none of them (it kept a copy of each before)."""
    scene = mv.open_scene(terrain_store)
    try:
        mv.render(scene, "flyover", frames=2, size=(160, 120), ranks=1, loading="complete")
        system = scene.system(RenderConfig(loading="complete"))
        pool = system.renderers()[1]
        cached = {k for k in pool.slots if system.cache.contains(k)}
        assert len(pool.slots) > 0 and cached == set()
        assert 0 < system.cache.peak_bytes <= system.cache.budget
    finally:
        scene.close()


@pytest.mark.parametrize("vscale,exaggeration", [(1.0, 1.0), (2.5, 1.7), (0.3, 3.0)])
def test_compact_hierarchy_gives_the_eager_float64_values(terrain_store, vscale, exaggeration):
    """Every column the walk reads equals the float64 arrays the hierarchy held before (same
    operations on the stored float32 values), bit for bit, at several scales."""
    st = TerrainStore(terrain_store)
    sq_err, dg_err, zmin, zmax = st.lod_arrays()
    h = PatchHierarchy(st.layout, sq_err, dg_err, zmin, zmax, spacing=st.spacing, vscale=vscale, exaggeration=exaggeration)
    Z, vs = exaggeration, vscale
    base = float(np.min(zmin[0])) * vs
    world = [base + Z * (np.asarray(z, np.float64) * vs - base) for z in zmin]
    world_hi = [base + Z * (np.asarray(z, np.float64) * vs - base) for z in zmax]
    for j in range(st.layout.J):
        n = 2**j
        lo, hi = np.full((2, n + 1, n + 1), np.inf), np.full((2, n + 1, n + 1), -np.inf)
        p, q = np.pad(world[j], 1, constant_values=np.inf), np.pad(world_hi[j], 1, constant_values=-np.inf)
        lo[0, :, :n], hi[0, :, :n] = np.minimum(p[:-1, 1:-1], p[1:, 1:-1]), np.maximum(q[:-1, 1:-1], q[1:, 1:-1])
        lo[1, :n, :], hi[1, :n, :] = np.minimum(p[1:-1, :-1], p[1:-1, 1:]), np.maximum(q[1:-1, :-1], q[1:-1, 1:])
        valid = np.isfinite(lo)
        eager = {
            "sq": ((world[j] + world_hi[j]) / 2, np.asarray(sq_err[j], np.float64) * vs * Z, world[j], world_hi[j]),
            "dg": (np.where(valid, (np.where(valid, lo, 0) + np.where(valid, hi, 0)) / 2, 0.0),
                   np.asarray(dg_err[j], np.float64) * vs * Z, lo, hi),
        }
        for name, tab in (("sq", h.sq_tab[j]), ("dg", h.dg_tab[j])):
            assert isinstance(tab[0], Lazy) and tab[1].dtype == np.float64
            ids = np.arange(len(tab[1]))
            for got, want in zip((tab[0], tab[2], tab[3], tab[4]), eager[name]):
                g = got[ids]
                assert g.dtype == np.float64 and np.array_equal(g, want.ravel()), (name, j)
    assert np.array_equal(h.sq_tab[st.layout.J][3][np.arange(4**st.layout.J)], world[st.layout.J].ravel())
