"""K-patch LOD: crack-free cuts (geometry and real renders), parallel equals serial, balance,
out-of-core behaviour under small budgets."""

import json

import numpy as np
import pytest

from conftest import RenderBatches, run_cli, summary
from massview.core.camera import Camera
from massview.core.config import RenderConfig
from massview.core.stats import FrameStats
from massview.core.task import Task
from massview.data.terrain import TerrainStore
from massview.lod.kpatch import PatchHierarchy, refine_uniform, select_front, watertight_problems


def hierarchy(path):
    st = TerrainStore(path)
    return st, PatchHierarchy(st.layout, *st.lod_arrays(), spacing=st.spacing, vscale=st.vertical_scale)


def cameras(h, width=480, height=360):
    lo, hi = h.bounds()
    c = (lo + hi) / 2
    ext = hi - lo
    zc = h.zmin[h.lay.J][h.lay.J and 2**h.lay.J // 2, 2**h.lay.J // 2]  # ground near the middle
    low = h.zmin[0].min()
    return {
        "top-down": Camera.look_at((c[0], c[1], hi[2] + 0.3 * ext[0]), (c[0] + 1e-3, c[1], 0), width=width, height=height, near=10, far=1e6),
        "grazing": Camera.look_at((lo[0] + 0.05 * ext[0], c[1], hi[2] + 20), (hi[0], c[1] + 0.1 * ext[1], hi[2] - 0.2 * (hi[2] - low)),
                                  width=width, height=height, near=1, far=1e6),
        "valley": Camera.look_at((c[0], c[1], zc + 40), (c[0] + 0.3 * ext[0], c[1] - 0.2 * ext[1], zc - 300),
                                 width=width, height=height, near=1, far=1e6),
    }


@pytest.mark.parametrize("view", ["top-down", "grazing", "valley"])
@pytest.mark.parametrize("tau", [0.5, 2.0])
def test_cut_is_watertight(terrain_store, view, tau):
    st, h = hierarchy(terrain_store)
    cam = cameras(h)[view]
    f = select_front(h, cam, tau)
    assert len(f) > 20
    tris = refine_uniform(f.ax, f.ay, f.lx, f.ly, f.rx, f.ry, 2 * h.lay.k)
    assert watertight_problems(tris, h.lay.S - 1) == []
    # the patch-level cut itself is conforming: every patch edge is shared whole by its neighbour
    pt = np.stack([np.stack([f.ax, f.ay], 1), np.stack([f.lx, f.ly], 1), np.stack([f.rx, f.ry], 1)], 1)
    assert watertight_problems(pt, h.lay.S - 1) == []
    # and patches sharing an edge differ by at most one bintree level
    side = h.lay.S
    e = np.concatenate([pt[:, [0, 1]], pt[:, [1, 2]], pt[:, [2, 0]]])
    code = np.sort(e[:, :, 0] * side + e[:, :, 1], axis=1) @ np.array([side * side, 1])
    depth = np.tile(f.depth, 3)
    order = np.argsort(code, kind="stable")
    same = code[order][1:] == code[order][:-1]
    gaps = np.abs(depth[order][1:] - depth[order][:-1])[same]
    assert same.sum() > 0 and gaps.max() <= 1


def test_partial_residency_stays_watertight(terrain_store):
    st, h = hierarchy(terrain_store)
    rng = np.random.default_rng(0)
    coin = {}

    def resident(lv, bi, bj):
        return np.array([coin.setdefault(k, rng.random() < 0.6) for k in zip(lv.tolist(), bi.tolist(), bj.tolist())], bool)

    for cam in cameras(h).values():
        f = select_front(h, cam, 1.0, resident)
        assert watertight_problems(refine_uniform(f.ax, f.ay, f.lx, f.ly, f.rx, f.ry, 2 * h.lay.k), h.lay.S - 1) == []
        full = select_front(h, cam, 1.0)
        assert len(f) <= len(full) and f.deferred > 0


def test_error_is_monotone_in_tau(terrain_store):
    st, h = hierarchy(terrain_store)
    cam = cameras(h)["grazing"]
    sizes = [len(select_front(h, cam, t)) for t in (4.0, 2.0, 1.0, 0.5)]
    assert sizes == sorted(sizes) and sizes[-1] > sizes[0]


@pytest.mark.parametrize("view", ["top-down", "grazing", "valley"])
def test_render_has_no_holes(terrain_store, view):
    """Each image column must show terrain as one run from the bottom row up (a heightfield seen
    from above cannot show sky below ground): a crack would let background through."""
    from massview.systems.terrain import TerrainSystem

    sysm = TerrainSystem(terrain_store, loading="complete")
    st, h = hierarchy(terrain_store)
    cam = cameras(h, 400, 300)[view]
    cfg = RenderConfig(width=400, height=300, tau=1.0, loading="complete")

    class Solo:
        def Get_size(self):
            return 1

        def allreduce(self, v, op=None):
            return v

    sysm.prepare_frame(Solo(), cam, cfg, FrameStats(0, 0))
    img = sysm.render(Task(0, cam.viewport), cam, cfg, FrameStats(0, 0))
    sysm.close()
    ground = img.depth < 1.0
    assert ground[-1].all(), "the bottom row should be terrain for these cameras"
    first_sky_from_bottom = np.where(~ground[::-1].any(axis=0), 0, np.argmin(ground[::-1], axis=0))
    for col in range(ground.shape[1]):
        run = ground[::-1, col]
        k = first_sky_from_bottom[col] if not run.all() else len(run)
        assert not run[k:].any(), f"background pixel inside the terrain in column {col}"


DECOMPS = ["sort-first:horizontal", "sort-first:vertical", "sort-first:grid", "sort-first:kd",
           "sort-last:kpatch", "sort-last:linear", "sort-last:quadtree"]
BALANCE_MODES = ("kpatch", "linear", "quadtree")


@pytest.fixture(scope="module")
def cases(tmp_path_factory, terrain_store):
    """Every multi-rank render of this module: one job per rank count (conftest.RenderBatches)."""
    size = ("--size", "320x240")
    return RenderBatches(tmp_path_factory, {
        **{f"{d}-{n}": (n, [terrain_store, "--decomposition", d, "--path", "flyover", "--frames", 2, *size, "--reference"])
           for d in DECOMPS for n in (2, 3, 4)},
        **{f"balance-{m}": (4, [terrain_store, "--decomposition", f"sort-last:{m}", "--path", "turn", "--frames", 4, *size])
           for m in BALANCE_MODES},
        "small-budgets": (2, [terrain_store, "--decomposition", "sort-first:vertical", "--path", "zoom", "--frames", 6, *size,
                              "--cache-mb", 4, "--gpu-mb", 4, "--loading", "async", "--reference"]),
    }, label="terrain")


@pytest.mark.mpi
@pytest.mark.parametrize("ranks", [2, 3, 4])
@pytest.mark.parametrize("decomposition", DECOMPS)
def test_terrain_parallel_equals_serial(cases, decomposition, ranks):
    out = cases.out(f"{decomposition}-{ranks}")
    s = summary(out)
    assert s["ranks"] == ranks and s["decomposition"] == decomposition
    if decomposition.startswith("sort-first"):
        assert s["max_abs_diff"] == 0
    else:
        assert s["diff_fraction"] < 1e-4
    recs = [json.loads(x) for x in (out / "stats.jsonl").read_text().splitlines()]
    assert all("patches" in r["counters"] and "front_patches" in r["counters"] for r in recs)
    assert sum(r["counters"]["patches"] for r in recs if r["frame"] == 1) >= recs[0]["counters"]["front_patches"] * 0.2


@pytest.mark.mpi
def test_kpatch_balance_on_turn(cases):
    out = {}
    for mode in BALANCE_MODES:
        d = cases.out(f"balance-{mode}")
        assert summary(d)["decomposition"] == f"sort-last:{mode}" and summary(d)["ranks"] == 4
        out[mode] = summary(d)["imbalance"]
        if mode == "kpatch":  # equal shares of the front: ranks differ by at most one patch (256 triangles) per frame
            recs = [json.loads(x) for x in (d / "stats.jsonl").read_text().splitlines()]
            for f in {r["frame"] for r in recs}:
                tri = [r["triangles"] for r in recs if r["frame"] == f]
                assert max(tri) - min(tri) <= 256
    assert out["kpatch"] <= 1.05  # complete loading (the default): small fronts at 320x240, one patch is ~3 %
    assert out["linear"] > out["kpatch"] and out["quadtree"] > out["kpatch"]


@pytest.mark.mpi
def test_small_budgets_never_wait_and_stay_correct(cases):
    """Async loading with budgets far below the data: frames complete, coarser where data is
    missing, and every rank still draws the same cut (reference matches)."""
    out = cases.out("small-budgets")
    s = summary(out)
    assert s["max_abs_diff"] == 0 and s["frames"] == 6 and s["ranks"] == 2
    recs = [json.loads(x) for x in (out / "stats.jsonl").read_text().splitlines()]
    assert sum(r["counters"].get("deferred_splits", 0) for r in recs) > 0  # data was missing at times
    assert sum(r["counters"].get("blocks_loaded", 0) for r in recs) > 0
    assert sum(r["triangles"] for r in recs if r["frame"] == 0) > 0  # walk7 L6: the first frame waits for the top block


def test_complete_loading_with_budgets_too_small_says_so(tmp_path, terrain_store):
    proc = run_cli("render", terrain_store, "--path", "zoom", "--frames", 2, "--size", "320x240", "--loading", "complete",
                   "--cache-mb", 1, "--gpu-mb", 2, "--tau", 0.5, "--out", tmp_path, "-q", check=False, timeout=120)
    assert proc.returncode != 0
    assert "do not fit the budgets (--cache-mb 1, --gpu-mb 2)" in proc.stderr and "Traceback" not in proc.stderr


def test_lookup_blocks_is_the_per_patch_grid_value():
    """lookup_blocks (one gather over the levels' grids flattened end to end; a plain gather for
    one level) == grids[level][bi, bj] patch by patch, for several levels, one level, none."""
    from massview.lod.kpatch import lookup_blocks

    rng = np.random.default_rng(2)
    grids = [rng.integers(-1, 500, (2 ** (4 - lv), 2 ** (4 - lv))) for lv in range(5)]
    lv = rng.integers(0, 5, 3000)
    bi = np.array([rng.integers(0, grids[v].shape[0]) for v in lv])
    bj = np.array([rng.integers(0, grids[v].shape[1]) for v in lv])
    want = np.array([grids[v][i, j] for v, i, j in zip(lv, bi, bj)])
    assert np.array_equal(lookup_blocks(grids, lv, bi, bj), want)
    one = lv == 2
    assert np.array_equal(lookup_blocks(grids, lv[one], bi[one], bj[one]), want[one])
    assert np.array_equal(lookup_blocks(grids, lv.astype(np.int8), bi, bj), want)
    assert len(lookup_blocks(grids, lv[:0], bi[:0], bj[:0])) == 0
    flags = [g > 200 for g in grids]
    assert np.array_equal(lookup_blocks(flags, lv, bi, bj), want > 200)


def test_stable_order_is_a_stable_argsort():
    from massview.render.terrain import _stable_order

    rng = np.random.default_rng(4)
    for hi in (7, 300, 65535, 65536, 10 ** 6):
        s = rng.integers(0, hi + 1, 20000).astype(np.int64)
        assert np.array_equal(_stable_order(s), np.argsort(s, kind="stable")), hi
    assert len(_stable_order(np.zeros(0, np.int64))) == 0
