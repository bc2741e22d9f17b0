"""The LOD stage rewrite (issue 20): the diamond walk selects exactly the patches the old
triangle walk (kept verbatim in massview.app.bench.lod_baseline) did, on real paths, with and
without missing blocks; a sort-first tile's own cut shows exactly the whole frame's patches in
the tile; and images drawn from either cut are identical."""

import json

import numpy as np
import pytest

from conftest import RenderBatches, run_cli, summary
from massview.app.bench import lod_baseline as old
from massview.app.bench.lod import _Rank
from massview.core.config import RenderConfig
from massview.core.paths import load_path
from massview.core.stats import FrameStats
from massview.core.task import Task
from massview.data.terrain import TerrainStore
from massview.lod import kpatch as new
from massview.parallel.decompose import grid_tiles

FIELDS = new.Front.FIELDS


def _hierarchies(path):
    st = TerrainStore(path)
    args, kw = (st.layout, *st.lod_arrays()), dict(spacing=st.spacing, vscale=st.vertical_scale)
    return st, old.PatchHierarchy(*args, **kw), new.PatchHierarchy(*args, **kw)


def _rows(f, idx=None):
    """(n, 13) patch records, sorted (a set comparison that ignores the order)."""
    a = np.stack([getattr(f, k).astype(np.float64) for k in FIELDS], 1)
    a = a if idx is None else a[idx]
    return a[np.lexsort(a.T[::-1])]


def _keys(calls):
    out = set()
    for lv, bi, bj, _ in calls:
        out.update(zip(lv.tolist(), bi.tolist(), bj.tolist()))
    return out


@pytest.fixture(scope="module")
def hier(terrain_store):
    return _hierarchies(terrain_store)


@pytest.mark.parametrize("path", ["flyover", "zoom", "turn", "forward"])
def test_new_walk_selects_the_old_cut(hier, path):
    st, ho, hn = hier
    lay = st.layout
    rng = np.random.default_rng(7)
    grids = [rng.random((2 ** (lay.L - lv),) * 2) < 0.7 for lv in range(lay.levels)]
    grids[lay.L][0, 0] = True
    p = load_path(path, *hn.bounds())
    waited = 0
    for at in (0.05, 0.5, 0.95):
        cam = p.camera(at, 640, 360)
        for tau in (2.0, 0.5):
            fo, fn = old.select_front(ho, cam, tau), new.select_front(hn, cam, tau)
            assert np.array_equal(_rows(fo), _rows(fn)) and fo.deferred == fn.deferred == 0
            ro, rn = [], []
            fo = old.select_front(ho, cam, tau, lambda lv, bi, bj: old.lookup_blocks(grids, lv, bi, bj), lambda *a: ro.append(a))
            fn = new.select_front(hn, cam, tau, grids, lambda *a: rn.append(a))
            assert np.array_equal(_rows(fo), _rows(fn))
            assert fo.deferred == fn.deferred and _keys(ro) == _keys(rn)
            waited += fn.deferred
            # the same patches are visible (culling by diamond sphere, box test where it crosses a plane)
            lo, hi = old.patch_boxes(ho, fo)
            from massview.lod.cull import boxes_in_frustum

            vo = np.flatnonzero(boxes_in_frustum(lo, hi, cam.frustum_planes()))
            assert np.array_equal(_rows(fo, vo), _rows(fn, new.visible_patches(hn, fn, cam)))
    assert waited > 0  # the missing blocks did hold splits back


@pytest.mark.parametrize("path", ["flyover", "zoom"])
def test_tile_cut_shows_the_frame_cut_in_the_tile(hier, path):
    """A tile's own cut, culled to the tile, is the whole-frame cut culled to the tile: the
    same patch records in the same order (so a tile draws exactly what the serial frame draws
    there); outside the tile it is coarser."""
    st, _, hn = hier
    lay = st.layout
    grids = [np.ones((2 ** (lay.L - lv),) * 2, bool) for lv in range(lay.levels)]
    grids[0][: 2 ** lay.L // 2] = False  # half of the finest blocks missing: residency holds some splits back
    p = load_path(path, *hn.bounds())
    for at in (0.1, 0.6):
        cam = p.camera(at, 480, 270)
        full = new.select_front(hn, cam, 0.5, grids)
        for tiles in (grid_tiles(480, 270, 1, 4), grid_tiles(480, 270, 2, 2), grid_tiles(480, 270, 3, 1)):
            sizes = []
            for vp in tiles:
                own = new.select_front(hn, cam, 0.5, grids, viewport=vp)
                a, b = own.take(new.visible_patches(hn, own, cam, vp)), full.take(new.visible_patches(hn, full, cam, vp))
                for k in FIELDS:
                    assert np.array_equal(getattr(a, k), getattr(b, k)), (vp, k)
                sizes.append(len(own))
            assert max(sizes) < len(full)


def test_images_from_old_and_new_cut_are_identical(terrain_store):
    """Real GL renders: the new front and the old walk's front draw bit-identical images."""
    from massview.systems.terrain import TerrainSystem

    st, ho, _ = _hierarchies(terrain_store)
    sysm = TerrainSystem(terrain_store, loading="complete")
    try:
        cfg = RenderConfig(width=320, height=240, tau=1.0, loading="complete")
        for path, at in (("flyover", 0.3), ("zoom", 0.7), ("turn", 0.5)):
            cam = load_path(path, *sysm.bounds).camera(at, 320, 240)
            sysm.prepare_frame(_Solo(), cam, cfg, FrameStats(0, 0))
            img_new = sysm.render(Task(0, cam.viewport), cam, cfg, FrameStats(0, 0))
            fo = old.select_front(ho, cam, cfg.tau)
            mine = sysm.front
            sysm.front = new.Front(*(getattr(fo, k) for k in FIELDS))
            img_old = sysm.render(Task(0, cam.viewport), cam, cfg, FrameStats(0, 0))
            sysm.front = mine
            assert len(fo) == len(mine)
            assert np.array_equal(img_new.color, img_old.color) and np.array_equal(img_new.depth, img_old.depth)
    finally:
        sysm.close()


class _Solo:
    def Get_size(self):
        return 1

    def allreduce(self, v, op=None):
        return v


PER_TILE = [("sort-first:horizontal", 4), ("sort-first:grid", 4), ("sort-first:vertical", 3)]


@pytest.fixture(scope="module")
def per_tile(tmp_path_factory, terrain_store):
    """The per-tile renders below, one job per rank count (conftest.RenderBatches)."""
    return RenderBatches(tmp_path_factory, {
        d: (n, [terrain_store, "--decomposition", d, "--path", "zoom", "--frames", 5, "--size", "320x240", "--cache-mb", 8,
                "--gpu-mb", 8, "--loading", "async", "--reference"]) for d, n in PER_TILE}, label="per-tile")


@pytest.mark.mpi
@pytest.mark.parametrize("decomposition,ranks", PER_TILE)
def test_per_tile_cuts_with_loads_assemble_to_the_serial_image(per_tile, decomposition, ranks):
    """Async loading with small budgets along a zoom: every rank cuts only its tile, blocks
    arrive while the frames run, and the tiles still assemble bit-exactly to the serial image
    of the whole frame's cut (recomputed from the agreed residency)."""
    out = per_tile.out(decomposition)
    s = summary(out)
    assert s["ranks"] == ranks and s["decomposition"] == decomposition
    assert s["max_abs_diff"] == 0 and s["frames"] == 5
    recs = [json.loads(x) for x in (out / "stats.jsonl").read_text().splitlines()]
    assert sum(r["counters"].get("blocks_loaded", 0) for r in recs) > 0
    assert sum(r["counters"].get("deferred_splits", 0) for r in recs) > 0  # data was missing at times


# -- issue 20, lod5: the faster stage selects today's cut, in today's order -----------------------
#
# Digests of the whole LOD stage's output recorded with the code before the lod5 speed-ups (main
# 8e7be8a) by ``_stage_digests`` below: per (path, at, τ) the front (every column, in order, the
# culling codes and the deferred count), the shading blocks wanted, and every task's share for
# sort-last (kpatch, linear, quadtree at 3 ranks) and sort-first (horizontal at 4 ranks, grid at
# 4: each rank's own tile cut and its visible patches). Any change of a value or of the order
# changes a digest.
STAGE_CASES = [("flyover", 0.3, 1.0), ("flyover", 0.8, 0.35), ("zoom", 0.6, 0.5), ("turn", 0.4, 2.0), ("forward", 0.9, 0.25)]
STAGE_DIGESTS = {
    'flyover@0.3/1.0': '8455def47fe640c87ab4',
    'flyover@0.3/1.0:kpatch': '24f8ec1965cbd78a184b',
    'flyover@0.3/1.0:linear': '8c18223300f54e6f9a77',
    'flyover@0.3/1.0:quadtree': 'ec4d4ced9633c329c657',
    'flyover@0.3/1.0:horizontal': '95d37d31f24f347afab9',
    'flyover@0.3/1.0:grid': 'c9dcf54f10c9b2208526',
    'flyover@0.8/0.35': '8816c51a459e7f56546c',
    'flyover@0.8/0.35:kpatch': '172ce84c5fce67d76381',
    'flyover@0.8/0.35:linear': 'a40ba8c55ab57875d70b',
    'flyover@0.8/0.35:quadtree': '3a8ed6542c53a8c2774a',
    'flyover@0.8/0.35:horizontal': '9b7d2174357ae0c2774d',
    'flyover@0.8/0.35:grid': '721257d9ea64642758b7',
    'zoom@0.6/0.5': 'be61dd19d8fae5a6cb11',
    'zoom@0.6/0.5:kpatch': '191ca7fc6082b2d3e061',
    'zoom@0.6/0.5:linear': 'df8fd66540c588e04484',
    'zoom@0.6/0.5:quadtree': '6473a1eb7aeb8e705e39',
    'zoom@0.6/0.5:horizontal': '3e0f99820339daba423f',
    'zoom@0.6/0.5:grid': '53b4f19325ebda68a0de',
    'turn@0.4/2.0': 'f9c6f8ce62bd5e94477e',
    'turn@0.4/2.0:kpatch': '29aa01b4355970064e3a',
    'turn@0.4/2.0:linear': 'e66497aec3c4daf0d5b9',
    'turn@0.4/2.0:quadtree': 'b70ec5e1796f2bde1f23',
    'turn@0.4/2.0:horizontal': '001ca68b197d3ce789fe',
    'turn@0.4/2.0:grid': 'c716de2d1da13475907f',
    'forward@0.9/0.25': 'ef3d75e9e7ee1a9d3c1d',
    'forward@0.9/0.25:kpatch': '26f19339d6ff1a8dddd6',
    'forward@0.9/0.25:linear': 'a8db50ae2829b927233b',
    'forward@0.9/0.25:quadtree': 'a273fa6fa908d46f5c75',
    'forward@0.9/0.25:horizontal': '8ae18d3759c586c56f8f',
    'forward@0.9/0.25:grid': '3238e79edf0e258f5e14',
}
# The same digests for the store's other input: on a CPU without AVX-512 the synthetic DEM differs
# in the last bit at some samples (numpy's float64 power; see tests/ingest_golden.py), so the cut
# differs too. Keyed by the store's heights/0 digest; recorded 2026-11-27 on such a host, where
# 8e7be8a (the code the digests above were recorded with) and main e13c53f gave these same values.
STAGE_DIGESTS_BY_INPUT = {
    'dfb36a217efd8addf9b61c3bb03b39ab652dda666c65a1aca52de2a6acae8295': {
        'flyover@0.3/1.0': 'e7e6ca7828bd24173b07',
        'flyover@0.3/1.0:grid': '28f31ff6e4eede69bc23',
        'flyover@0.3/1.0:horizontal': '5293e209fc893e63c0f5',
        'flyover@0.3/1.0:kpatch': '24f8ec1965cbd78a184b',
        'flyover@0.3/1.0:linear': '8c18223300f54e6f9a77',
        'flyover@0.3/1.0:quadtree': 'ec4d4ced9633c329c657',
        'flyover@0.8/0.35': '74d98fb2ce84ec573f58',
        'flyover@0.8/0.35:grid': '1a229638b9aecd16b97a',
        'flyover@0.8/0.35:horizontal': '40dc71544c21856ee172',
        'flyover@0.8/0.35:kpatch': '172ce84c5fce67d76381',
        'flyover@0.8/0.35:linear': 'a40ba8c55ab57875d70b',
        'flyover@0.8/0.35:quadtree': '3a8ed6542c53a8c2774a',
        'forward@0.9/0.25': '523cb3a0a4a88ea9d78c',
        'forward@0.9/0.25:grid': '727eff4751a5b32116ba',
        'forward@0.9/0.25:horizontal': '406d0946a8807901daac',
        'forward@0.9/0.25:kpatch': '26f19339d6ff1a8dddd6',
        'forward@0.9/0.25:linear': 'a8db50ae2829b927233b',
        'forward@0.9/0.25:quadtree': 'a273fa6fa908d46f5c75',
        'turn@0.4/2.0': '2e96010a499fc58d6d6d',
        'turn@0.4/2.0:grid': 'aae67672af099dcbe12d',
        'turn@0.4/2.0:horizontal': 'e42b89582aa1544cf3c7',
        'turn@0.4/2.0:kpatch': '29aa01b4355970064e3a',
        'turn@0.4/2.0:linear': 'e66497aec3c4daf0d5b9',
        'turn@0.4/2.0:quadtree': 'b70ec5e1796f2bde1f23',
        'zoom@0.6/0.5': '27454e45f1d5a0a6f6d3',
        'zoom@0.6/0.5:grid': '2ee464d874e7c0cc9cb9',
        'zoom@0.6/0.5:horizontal': 'b7840be6e044609ea72e',
        'zoom@0.6/0.5:kpatch': '191ca7fc6082b2d3e061',
        'zoom@0.6/0.5:linear': 'df8fd66540c588e04484',
        'zoom@0.6/0.5:quadtree': '6473a1eb7aeb8e705e39',
    },
}


def recorded_stage_digests(store) -> tuple[str, dict]:
    """(the store's heights/0 digest, the recorded stage digests for that input)."""
    from ingest_golden import input_digest

    key = input_digest(store)
    rec = STAGE_DIGESTS_BY_INPUT.get(key, STAGE_DIGESTS)
    # sort-last:linear changed on purpose (2026-11-28: a patch goes by the finest M-block under it, not by
    # the block it draws from, which sent every coarse block's patch to rank 0): its shares are checked
    # against an oracle in test_linear_shares_are_x_slabs_of_the_front instead of the recorded digests
    return key, {k: v for k, v in rec.items() if not k.endswith(":linear")}


def _stage_digests(store) -> dict:
    import hashlib

    from massview.systems.terrain import TerrainSystem

    def h(*arrays) -> str:
        d = hashlib.sha256()
        for a in arrays:
            a = np.ascontiguousarray(a)
            d.update(str((a.dtype.str, a.shape)).encode())
            d.update(a.tobytes())
        return d.hexdigest()[:20]

    out = {}
    sysm = TerrainSystem(store, loading="complete")
    try:
        w, hh = 400, 240
        for path, at, tau in STAGE_CASES:
            cam = load_path(path, *sysm.bounds).camera(at, w, hh)
            key = f"{path}@{at}/{tau}"
            for mode in ("kpatch", "quadtree"):
                cfg = RenderConfig(width=w, height=hh, tau=tau, loading="complete", decomposition=f"sort-last:{mode}")
                sysm.prepare_frame(_Rank(0, 1), cam, cfg, FrameStats(0, 0))
                f = sysm.front
                out[key] = h(*(getattr(f, k) for k in FIELDS), f.code, np.array([f.deferred]), sysm._tex_ids)
                out[f"{key}:{mode}"] = h(*(sysm.select(t, cam, cfg) for t in sysm.plan(cam, cfg, 3)))
            for layout in ("horizontal", "grid"):
                cfg = RenderConfig(width=w, height=hh, tau=tau, loading="complete", decomposition=f"sort-first:{layout}")
                shares = []
                for r in range(4):
                    sysm.prepare_frame(_Rank(r, 4), cam, cfg, FrameStats(0, 0))
                    f = sysm.front
                    shares += [*(getattr(f, k) for k in FIELDS), f.code, sysm.select(sysm.plan(cam, cfg, 4)[r], cam, cfg)]
                out[f"{key}:{layout}"] = h(*shares)
    finally:
        sysm.close()
    return out


def test_stage_output_is_todays(terrain_store):
    """The whole LOD stage (front, shading wants, every task's share) is bit for bit what it was
    before the lod5 speed-ups, in the same order, for sort-last and per-tile sort-first."""
    key, want = recorded_stage_digests(terrain_store)
    got = _stage_digests(terrain_store)
    assert got.keys() == want.keys()
    bad = [k for k in got if got[k] != want[k]]
    assert not bad, f"{bad} (input heights/0 {key[:16]})"


def test_shading_pyramid_is_shading_blocks(hier):
    """ShadingPyramid (boxes once per hierarchy) wants exactly shading_blocks' blocks and priorities."""
    from massview.lod.texlod import ShadingPyramid, shading_blocks

    st, _, hn = hier
    mm = [st.block_minmax(lv) for lv in range(st.layout.levels)]
    for Z in (1.0, 2.5):
        zmap = lambda z: hn.base + Z * (z * hn.vs - hn.base)  # noqa: E731
        pyr = ShadingPyramid(mm, st.layout.M, st.spacing, zmap)
        n = 0
        for path in ("flyover", "zoom", "turn", "forward"):
            p = load_path(path, *hn.bounds())
            for at in np.linspace(0, 1, 9):
                for size, limit in (((640, 360), 4096), ((1920, 1080), 4096), ((320, 240), 6)):
                    cam = p.camera(float(at), *size)
                    a, b = shading_blocks(mm, st.layout.M, st.spacing, zmap, cam, limit), pyr.blocks(cam, limit)
                    for x, y in zip(a, b):
                        assert x.dtype == y.dtype and np.array_equal(x, y)
                    n += len(a[0])
        assert n > 0


def test_bench_lod_against_another_checkout(terrain_store, tmp_path):
    """``bench lod --against SRC`` times another checkout's stage beside this one in one process
    and checks their output equal (here: this checkout against itself), with the other
    checkout's compiled LOD kernels loaded before timing (it timed them walking with numpy:
    8.0 ms against 3.9 for the same code at 20 k patches); a directory without a massview
    package is a clear error naming the option."""
    from pathlib import Path

    import massview

    src = Path(massview.__file__).parents[1]
    out = run_cli("bench", "lod", "--store", terrain_store, "--targets", "3000", "--frames", "2", "--repeat", "1", "--tiles", "2",
                  "--against", src).stdout
    assert "(before) vs this checkout" in out and "identical" in out and "DIFFERENT" not in out
    assert "loading (compiling) its LOD kernels before timing" in out
    bad = run_cli("bench", "lod", "--store", terrain_store, "--against", tmp_path, check=False)
    assert bad.returncode != 0 and "--against" in bad.stderr + bad.stdout


def test_front_block_ids_written_by_the_walk(hier):
    """The block ids the walk writes into the front (and keeps through ``take``) are the ones
    ``Front.block_ids`` computes from the front's columns."""
    import dataclasses

    from massview.lod.blockindex import BlockIndex

    st, _, hn = hier
    lay = st.layout
    index = BlockIndex(lay.levels, lay.L)
    grids = [np.ones((2 ** (lay.L - lv),) * 2, bool) for lv in range(lay.levels)]
    grids[0][::2] = False
    for path, at, tau, vp in (("flyover", 0.3, 0.5, None), ("zoom", 0.7, 0.2, None), ("turn", 0.5, 1.0, grid_tiles(480, 270, 2, 2)[1])):
        cam = load_path(path, *hn.bounds()).camera(at, 480, 270)
        for res in (None, grids):
            f = new.select_front(hn, cam, tau, res, viewport=vp)
            assert f.bid is not None and len(f) > 100
            plain = dataclasses.replace(f, bid=None)
            assert np.array_equal(f.block_ids(index.offset, index.nb), plain.block_ids(index.offset, index.nb))
            idx = np.arange(0, len(f), 3)
            assert np.array_equal(f.take(idx).block_ids(index.offset, index.nb), plain.take(idx).block_ids(index.offset, index.nb))


def test_linear_shares_are_x_slabs_of_the_front(terrain_store):
    """sort-last:linear: the shares of 3 tasks partition the visible front (every patch once, in
    front order), and a patch is in share i exactly when the origin x of the finest M-block under
    its centroid lies in [i/3, (i+1)/3) of the grid: an oracle written from the patch corners."""
    from massview.systems.terrain import TerrainSystem

    sysm = TerrainSystem(terrain_store, loading="complete")
    try:
        lay = sysm.lay
        nb0, span0 = lay.blocks(0), lay.M - 1
        for path, at, tau in STAGE_CASES:
            cam = load_path(path, *sysm.bounds).camera(at, 400, 240)
            cfg = RenderConfig(width=400, height=240, tau=tau, loading="complete", decomposition="sort-last:linear")
            sysm.prepare_frame(_Rank(0, 1), cam, cfg, FrameStats(0, 0))
            shares = [sysm.select(t, cam, cfg) for t in sysm.plan(cam, cfg, 3)]
            f = sysm.front
            vis = np.sort(np.concatenate(shares))
            assert len(np.unique(vis)) == len(vis), "a patch in two shares"
            full = RenderConfig(width=400, height=240, tau=tau, loading="complete", decomposition="sort-last:kpatch")
            assert np.array_equal(vis, np.concatenate([sysm.select(t, cam, full) for t in sysm.plan(cam, full, 1)]))
            for i, share in enumerate(shares):
                assert np.all(np.diff(share) > 0)
                cx = (f.ax[share].astype(np.int64) + f.lx[share] + f.rx[share]) // 3
                x = np.minimum(cx // span0, nb0 - 1) / nb0
                assert np.all((x >= i / 3) & (x < (i + 1) / 3)), f"{path}@{at}: share {i} holds patches of another slab"
    finally:
        sysm.close()
