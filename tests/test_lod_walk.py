"""The diamond walk's shortcuts (issue 20, a faster LOD stage), each against the geometry it
replaces: patch records from per-(depth, parity, half) tables, child blocks from lattice shifts,
the walked depths against the same depths decided as one batch, and the terrain system's
per-frame state (agreed residency read in place, requests, deferred splits) across a path with
jumps while blocks load."""

import numpy as np
import pytest

from massview.app.bench import lod_baseline as old
from massview.core.config import RenderConfig
from massview.core.paths import load_path
from massview.core.stats import FrameStats
from massview.data.terrain import TerrainStore
from massview.data.terrain.layout import TerrainLayout
from massview.lod import kpatch as new
from massview.lod import kpatch_walk as walk
from massview.lod.kpatch_cut import Dims, Residency, draw_level, edge_halves, patch_vertices, square_halves
from massview.lod.kpatch_top import TopBatch
from massview.parallel.decompose import grid_tiles
from test_lod_stage import _keys

FIELDS = new.Front.FIELDS
LAYOUTS = [(1500, 129, 3), (2049, 257, 17), (4097, 257, 5), (3000, 513, 129)]


def _diamonds(rng, t: int, count: int):
    """Random diamonds of depth t (every one where there are fewer): (o, v, u)."""
    n = 2 ** (t // 2)
    if t % 2 == 0:
        v, u = rng.integers(0, n, count), rng.integers(0, n, count)
        return np.zeros(count, np.int64), v, u
    o = rng.integers(0, 2, count)
    a, b = rng.integers(0, n + 1, count), rng.integers(0, n, count)  # along the edge's normal / along the edge
    return o, np.where(o == 0, a, b), np.where(o == 0, b, a)


@pytest.mark.parametrize("rows,M,K", LAYOUTS)
def test_patch_records_match_the_geometry(rows, M, K):
    """Tabled offsets + (u·a, v·a) give exactly patch_vertices' vertices, the block holding the
    patch centroid ((ay + ly + ry) // 3 >> (level + m)), depth, block level and stride."""
    lay = Dims(TerrainLayout(rows, rows, M, K))
    rng = np.random.default_rng(rows)
    keys, rows_, wants = [], [], []
    for t in range(2 * lay.J + 1):
        o, v, u = _diamonds(rng, t, 300)
        half = rng.integers(0, 2, len(v)).astype(bool)
        key = walk.pack(o, v, u, ~half, half)
        row = 16 * t + (u & 1) + 2 * (v & 1) + 4 * half + 8 * o
        out = np.zeros((11, len(v)), np.int64)
        walk._patch_records(lay, key, row, out, [(0, len(v), t)])
        ax, ay, lx, ly, rx, ry = patch_vertices(t, o, v, u, half, lay.square_side(t // 2))
        lvl = draw_level(lay.J, t)
        blvl = min(lvl, lay.L)
        span = (lay.M - 1) << blvl
        want = [ax, ay, lx, ly, rx, ry, np.full(len(v), t), np.full(len(v), blvl), (ay + ly + ry) // 3 // span,
                (ax + lx + rx) // 3 // span, np.full(len(v), 2 ** (lvl - blvl))]
        for k, (got, exp) in enumerate(zip(out, want)):
            assert np.array_equal(got, exp), (t, FIELDS[k])
        keys.append(key), rows_.append(row), wants.append(np.stack(want))
    # every depth in one call, one span each (as emit writes a front)
    n = np.cumsum([0] + [len(k) for k in keys])
    out = np.zeros((11, n[-1]), np.int64)
    walk._patch_records(lay, np.concatenate(keys), np.concatenate(rows_), out, [(n[t], n[t + 1], t) for t in range(len(keys))])
    assert np.array_equal(out, np.concatenate(wants, axis=1))


@pytest.mark.parametrize("rows,M,K", LAYOUTS)
def test_child_blocks_from_lattice_shifts_match_centroids(rows, M, K):
    """The residency the walk checks for a diamond's children — (v ≫ d, u ≫ d), one row up or
    one column left for half 0 of an edge — is the block of each existing half's centroid at
    the children's level, as the walk computed it before (clipped centroid division)."""
    lay = Dims(TerrainLayout(rows, rows, M, K))
    rng = np.random.default_rng(rows + 1)
    for t in range(2 * lay.J):
        o, v, u = _diamonds(rng, t, 400)
        n = 2 ** (t // 2)
        w = np.where(o == 0, v, u)
        ex = [w >= 1, w < n] if t % 2 else [np.ones(len(v), bool)] * 2
        seen = []
        res = Residency(lambda lv, bi, bj: seen.append((lv, bi, bj)) or np.ones(len(bi), bool), lay.levels, lay.L)
        hb = ex[0] + 2 * ex[1].astype(np.int64)
        crit = np.ones(len(v), bool)
        walk._resident(lay, res, None, t, o, v, u, hb, crit, np.ones(len(v)), crit.copy())
        blvl = min(draw_level(lay.J, t + 1), lay.L)
        span, nb = (lay.M - 1) << blvl, 2 ** (lay.L - blvl)
        ap0, ap1, pq = edge_halves(o, v, u, lay.square_side(t // 2)) if t % 2 else square_halves(v, u, lay.square_side(t // 2))
        for k, ap in enumerate((ap0, ap1)):
            lv, bi, bj = seen[k if t % 2 else 0]
            assert (lv == blvl).all()
            e = ex[k]
            assert np.array_equal(bi[e], np.clip((pq[1] + ap[1]) // 3 // span, 0, nb - 1)[e]), (t, k)
            assert np.array_equal(bj[e], np.clip((pq[0] + ap[0]) // 3 // span, 0, nb - 1)[e]), (t, k)


def _rows(f, idx=None):
    code = np.zeros(len(f)) if f.code is None else f.code.astype(np.float64)
    a = np.stack([getattr(f, k).astype(np.float64) for k in FIELDS] + [code], 1)
    a = a if idx is None else a[idx]
    return a[np.lexsort(a.T[::-1])]


@pytest.fixture(scope="module")
def shallow(terrain_store):
    """The test store's hierarchy twice: the default one (depths 0–13 as one batch: with J = 7
    only the leaves are walked) and one whose batch stops at depth 3, so the walk decides
    depths 4–13 key by key."""
    st = TerrainStore(terrain_store)
    args, kw = (st.layout, *st.lod_arrays()), dict(spacing=st.spacing, vscale=st.vertical_scale)
    batched, walked = new.PatchHierarchy(*args, **kw), new.PatchHierarchy(*args, **kw)
    walked.top = TopBatch(walked, 2)
    return st, batched, walked, old.PatchHierarchy(*args, **kw)


@pytest.mark.parametrize("path", ["flyover", "zoom", "turn"])
def test_walked_depths_equal_the_batch_and_the_old_walk(shallow, path):
    """Depths walked as keys and the same depths decided as one batch select the same patches
    (with their culling codes), requests and deferred splits, with blocks missing and for
    sort-first tiles; both are the old triangle walk's cut."""
    st, hb, hw, ho = shallow
    lay = st.layout
    rng = np.random.default_rng(11)
    grids = [rng.random((2 ** (lay.L - lv),) * 2) < 0.75 for lv in range(lay.levels)]
    grids[lay.L][0, 0] = True
    p = load_path(path, *hb.bounds())
    waited = 0
    for at in (0.1, 0.5, 0.9):
        cam = p.camera(at, 480, 270)
        for tau, vp in ((0.6, None), (1.5, None), (0.6, grid_tiles(480, 270, 2, 2)[3])):
            got = []
            for h in (hb, hw):
                calls = []
                f = new.select_front(h, cam, tau, grids, lambda *a: calls.append(a), vp)
                got.append((f, _keys(calls)))
            (fb, rb), (fw, rw) = got
            assert np.array_equal(_rows(fb), _rows(fw)) and fb.deferred == fw.deferred and rb == rw
            assert np.array_equal(_rows(fb, new.visible_patches(hb, fb, cam, vp)), _rows(fw, new.visible_patches(hw, fw, cam, vp)))
            if vp is None:
                calls = []
                fo = old.select_front(ho, cam, tau, lambda lv, bi, bj: old.lookup_blocks(grids, lv, bi, bj), lambda *a: calls.append(a))
                assert np.array_equal(_rows(fo)[:, :13], _rows(fw)[:, :13]) and fo.deferred == fw.deferred and _keys(calls) == rw
            waited += fw.deferred
    assert waited > 0


def _wait_idle(sysm) -> None:
    """Wait until the loader has staged every requested block in the RAM cache (the next
    prepare_frame uploads them), as complete loading does between frames."""
    import time

    t0 = time.monotonic()
    while not sysm.cache.idle() and time.monotonic() - t0 < 60:
        time.sleep(0.002)


def test_system_cut_across_jumps_while_blocks_load(terrain_store):
    """The terrain system's own cut (agreed residency read in place from the flat agreement,
    the walk doing depths 4–13) along cameras that jump between paths with small budgets and
    asynchronous loading: every frame it equals the old walk's cut on a copy of that frame's
    agreed residency, with the same deferred splits and the same requested blocks."""
    from massview.parallel.runtime import self_comm
    from massview.systems.terrain import TerrainSystem

    sysm = TerrainSystem(terrain_store, cache_bytes=6 << 20, gpu_bytes=6 << 20)
    try:
        sysm.h.top = TopBatch(sysm.h, 2)
        ho = old.PatchHierarchy(sysm.lay, *sysm.store.lod_arrays(), spacing=sysm.store.spacing,
                                vscale=sysm.store.vertical_scale)
        cfg = RenderConfig(width=320, height=240, tau=0.8)
        b = sysm.bounds
        shots = [("zoom", 0.9), ("flyover", 0.1), ("zoom", 0.92), ("turn", 0.5), ("flyover", 0.8), ("zoom", 0.95),
                 ("zoom", 0.95), ("forward", 0.3), ("flyover", 0.12), ("zoom", 0.9)]
        deferred = loaded = 0
        comm = self_comm()
        sysm.prepare_frame(comm, load_path("zoom", *b).camera(0.0, 320, 240), cfg, FrameStats(0, 0))
        _wait_idle(sysm)  # the top block: the cut starts once it is resident
        for path, at in shots:
            cam = load_path(path, *b).camera(at, 320, 240)
            stats = FrameStats(0, 0)
            sysm.prepare_frame(comm, cam, cfg, stats)
            grids = [g.copy() for g in sysm._grids]
            calls = []
            fo = old.select_front(ho, cam, cfg.tau, lambda lv, bi, bj: old.lookup_blocks(grids, lv, bi, bj), lambda *a: calls.append(a))
            f = sysm.front
            assert np.array_equal(_rows(fo)[:, :13], _rows(f)[:, :13]) and fo.deferred == f.deferred, (path, at)
            wanted = sysm._blocks.mask(sysm._blocks.ids(*np.array(sorted(_keys(calls)), np.int64).reshape(-1, 3).T))
            assert np.array_equal(wanted, sysm._want_mask), (path, at)
            deferred += f.deferred
            loaded += stats.counters.get("blocks_loaded", 0)
            _wait_idle(sysm)
        assert deferred > 0 and loaded > 0  # blocks were missing and arrived along the way
    finally:
        sysm.close()
