"""T2 (Röttger) without MPI: the per-node table, crack-free conforming meshes with neighbouring
leaves at most one level apart (culling off, union of every computation rank's portion, real
and rough synthetic DEMs, grazing/top-down/close/far cameras, smallest and largest C), the
exact partition, windowed reads, the fan encoding and the roles rank map."""

import dataclasses

import numpy as np
import pytest

from conftest import run_cli
from massview.core.errors import ConfigError, StoreError
from massview.data.terrain import ArraySource, TerrainStore, prepare_terrain
from massview.data.terrain.roettger import RoettgerTable, compute_table, has_table, prepare_roettger
from massview.lod.fanstream import FanReceiver, FanSender, decode_message
from massview.lod.roettger import (C_RANGE, RoettgerParams, k_factor, local_d2, partition_depth, portion_nodes,
                                   propagate_into)
from massview.parallel.roles import Role, assign_roles
from massview.systems.roettger_portion import LayerInfo, LayerPortion


def real_dem() -> np.ndarray:
    """A real DEM (USGS, Jacksboro fault, 344 × 403, ~90 m) shipped with matplotlib."""
    from matplotlib import cbook

    return cbook.get_sample_data("jacksboro_fault_dem.npz")["elevation"].astype(np.float32)


def rough_dem(rows=300, cols=237, seed=5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((rows, cols)).astype(np.float32) * 40
    a[::7] += 300  # ridges and cliffs
    a[:, 100:] += 500
    return a


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    out = {}
    for name, arr in (("real", real_dem()), ("rough", rough_dem())):
        p = tmp_path_factory.mktemp("roettger") / f"{name}.zarr"
        prepare_terrain(ArraySource(arr, name), p, block=129, color=None)
        prepare_roettger(p, C_min=2.0)  # valid for every C in [2, 64]
        out[name] = p
    return out


# -- table -------------------------------------------------------------------------------------
def test_local_d2_is_the_largest_midpoint_deviation_over_d():
    g = np.zeros((3, 3), np.float32)
    g[0, 1] = 4.0  # top midpoint 4 above the mean of its corners
    g[1, 1] = -2.0  # centre 2 below both diagonals
    assert local_d2(g, 2)[0, 0] == pytest.approx(2.0)
    g[1, 1] = -10.0
    assert local_d2(g, 2)[0, 0] == pytest.approx(5.0)


def test_propagation_reaches_the_neighbour_across_an_edge():
    fine = np.zeros((4, 4), np.float32)
    fine[1, 2] = 1.0  # bottom-left child of coarse (0, 1): touches coarse (1, 1) from above, (0, 0) from the right
    coarse = np.zeros((2, 2), np.float32)
    propagate_into(coarse, fine, 0, 0.5)
    assert coarse[0, 1] == 0.5 and coarse[1, 1] == 0.5 and coarse[0, 0] == 0.5 and coarse[1, 0] == 0.0


def test_table_is_saturated_with_neighbours(stores):
    st = TerrainStore(stores["rough"])
    d2 = compute_table(st, 2.0)
    K = k_factor(2.0)
    for t in range(len(d2) - 1):
        fine, coarse = d2[t + 1], d2[t]
        want = np.zeros_like(coarse)
        propagate_into(want, fine, 0, K)
        assert np.all(coarse >= want - 1e-6)
    assert RoettgerTable(st).C_min == 2.0


def test_store_without_table_names_the_command(tmp_path):
    prepare_terrain(ArraySource(rough_dem(40, 50), "x"), tmp_path / "s.zarr", block=129, color=None)
    import zarr

    zarr.open_group(str(tmp_path / "s.zarr"), mode="r+").attrs["roettger"] = None  # an older store
    with pytest.raises(StoreError, match="massview prepare roettger"):
        RoettgerTable(TerrainStore(tmp_path / "s.zarr"))
    proc = run_cli("render", tmp_path / "s.zarr", "--system", "roettger", "--ranks", "2", "-q", check=False)
    assert proc.returncode != 0 and "massview prepare roettger" in proc.stderr and "Traceback" not in proc.stderr
    run_cli("prepare", "roettger", tmp_path / "s.zarr", "-q")
    assert has_table(TerrainStore(tmp_path / "s.zarr"))


# -- conforming mesh ------------------------------------------------------------------------------
_PORTIONS: dict = {}


def _union(path, C: int, Cres: float, eye, c: float):
    """Leaves and fans of every computation rank's portion (culling off), over the whole
    padded square (rows = cols = S so that no node is dropped as padding)."""
    info = LayerInfo.of(path)
    info = dataclasses.replace(info, rows=info.S, cols=info.S)
    depth0 = partition_depth(C)
    if (path, C) not in _PORTIONS:
        _PORTIONS[(path, C)] = [LayerPortion(info, nodes, depth0) for nodes in portion_nodes(depth0, C)]
    leaves, fans = [], []
    for p in _PORTIONS[(path, C)]:
        lv = p.select(eye, RoettgerParams(C=Cres, c=c, depth0=depth0))
        leaves.append(lv)
        fans.append(p.fans(lv)[0])
    return info, leaves, fans


def _check_conforming(info, leaves, fans):
    n, S = info.n, info.S
    depth = np.full((S - 1, S - 1), -1, np.int64)
    cover = np.zeros((S - 1, S - 1), np.int64)
    t_all = np.concatenate([lv.depth for lv in leaves])
    r_all = np.concatenate([lv.row for lv in leaves])
    c_all = np.concatenate([lv.col for lv in leaves])
    for t in np.unique(t_all):
        d, s = 2 ** (n - int(t)), t_all == t
        g = np.zeros((2 ** int(t),) * 2, np.int64)
        np.add.at(g, (r_all[s], c_all[s]), 1)
        g = np.repeat(np.repeat(g, d, 0), d, 1)
        cover += g
        depth[g > 0] = t
    assert (cover == 1).all(), "leaves overlap or leave a hole"
    jump = max(np.abs(np.diff(depth, axis=0)).max(), np.abs(np.diff(depth, axis=1)).max())
    assert jump <= 1, f"neighbouring leaves {jump} levels apart"
    tris = []
    for f in fans:
        off = np.concatenate([[0], np.cumsum(f.lengths.astype(np.int64))])
        idx = f.index.astype(np.int64)
        for L in np.unique(f.lengths):
            sel = np.flatnonzero(f.lengths == L)
            v = idx[off[sel][:, None] + np.arange(L)]
            for i in range(1, L - 1):
                tris.append(np.stack([v[:, 0], v[:, i], v[:, i + 1]], 1))
    tris = np.concatenate(tris)
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    keys, count = np.unique(e[:, 0] * S * S + e[:, 1], return_counts=True)
    a, b = keys // (S * S), keys % (S * S)
    ar, ac, br, bc = a // S, a % S, b // S, b % S
    border = ((ar == br) & ((ar == 0) | (ar == S - 1))) | ((ac == bc) & ((ac == 0) | (ac == S - 1)))
    assert np.all(count[~border] == 2), f"{np.count_nonzero(count[~border] != 2)} interior edges not shared by exactly two triangles"
    assert np.all(count[border] == 1)
    return len(np.unique(depth))


@pytest.mark.parametrize("dem", ["real", "rough"])
@pytest.mark.parametrize("Cres", [C_RANGE[0], C_RANGE[1]])
def test_union_is_conforming_for_every_camera(stores, dem, Cres):
    info = LayerInfo.of(stores[dem])
    w = (info.S - 1) * info.spacing[0]
    z = info.zrange[1] * info.vscale
    cams = {"top-down": (w / 2, -w / 2, z + w), "grazing": (-0.05 * w, -0.4 * w, z + 0.01 * w),
            "close": (0.3 * w, -0.35 * w, z + 0.02 * w), "far": (-6 * w, 5 * w, z + 2 * w)}
    levels = set()
    for C in (1, 3):
        for name, eye in cams.items():
            for c in (3.0, 300.0):
                levels.add(_check_conforming(*_union(stores[dem], C, Cres, eye, c)))
    assert max(levels) >= 4  # the meshes are adaptive, not uniform


def test_c_outside_the_proven_range_is_refused():
    with pytest.raises(ConfigError, match=r"\[2, 64\]"):
        RoettgerParams(C=1.5)


# -- partition and windowed reads -------------------------------------------------------------------
@pytest.mark.parametrize("C", [1, 2, 3, 4, 5, 16])
def test_partition_is_exact_contiguous_and_balanced(C):
    L = partition_depth(C)
    smallest = next(k for k in range(10) if 4**k >= C)
    assert L == (smallest if 4**smallest == C else smallest + 1)
    parts = portion_nodes(L, C)
    allnodes = np.concatenate(parts)
    assert len({tuple(x) for x in allnodes}) == 4**L == len(allnodes)
    sizes = [len(p) for p in parts]
    assert max(sizes) - min(sizes) <= 1


@pytest.mark.parametrize("C", [2, 3, 5])
@pytest.mark.parametrize("extent", [(0.49, 0.73), (1.0, 0.2), (0.3, 1.0)])
def test_partition_of_a_non_square_dem_shares_the_data(C, extent):
    """A DEM filling only part of its padded square: every rank's run holds near-equal counts of
    the nodes with data (before, a rank could own padding alone and draw nothing: walk5 M1),
    the runs still cover every node once, and the depth goes deeper only as far as needed."""
    from massview.lod.roettger import data_nodes

    L = partition_depth(C, extent)
    assert L >= partition_depth(C) and data_nodes(L, extent).sum() >= 4**partition_depth(C)
    parts = portion_nodes(L, C, extent)
    allnodes = np.concatenate(parts)
    assert len({tuple(x) for x in allnodes}) == 4**L == len(allnodes)
    data = data_nodes(L, extent)
    counts = [int(data[p[:, 0], p[:, 1]].sum()) for p in parts]
    assert min(counts) > 0 and max(counts) - min(counts) <= 1
    full = portion_nodes(partition_depth(C), C, (1.0, 1.0))
    assert all(np.array_equal(a, b) for a, b in zip(full, portion_nodes(partition_depth(C), C)))  # square: as before


def test_a_rank_reads_only_its_portion(stores):
    info = LayerInfo.of(stores["real"])
    whole = LayerPortion(info, np.array([[0, 0]]), 0)
    parts = [LayerPortion(info, nodes, 1) for nodes in portion_nodes(1, 4)]
    for p in parts:  # M-blocks of its quarter (4 of 16) and its table windows (with the halo)
        assert p.bytes_read < 0.4 * whole.bytes_read
        assert p.heights.size <= 0.3 * info.S**2  # only its quarter's heights are held


# -- encoding -----------------------------------------------------------------------------------
def test_fan_stream_round_trips_at_a_16385_index_range():
    rng = np.random.default_rng(1)
    top = 16385 * 16385 - 1
    held_expected = None
    snd, rcv = FanSender(2), FanReceiver(2)
    keys0 = np.sort(rng.choice(top, 500, replace=False)).astype(np.int64)
    prev = keys0
    for frame in range(3):
        keys = keys0[rng.random(len(keys0)) < 0.8] if frame else keys0
        layers, expected = [], []
        for layer in range(2):
            lengths = rng.integers(6, 11, len(keys)).astype(np.uint32)
            lengths[:] = 6 + (keys % 5)  # a fan's length is a function of its identity
            index = np.concatenate([np.full(L, k, np.uint32) for L, k in zip(lengths, keys)]) if layer else \
                np.concatenate([np.arange(top - L + 1, top + 1, dtype=np.uint32) for L in lengths])
            height = (index.astype(np.float64) % 9973).astype(np.float32) * 0.5
            layers.append((keys * 16 + layer, lengths, index, height))
            expected.append((lengths, index, height))
        msg, st = snd.encode(layers)
        held = rcv.apply(np.frombuffer(msg, np.uint8))
        for (lengths, index, height), h in zip(expected, held):
            # the receiver holds the same fans (order: kept, then new; compare as sets of fans)
            assert sorted(map(tuple, np.split(h.index, np.cumsum(h.lengths)[:-1]))) == \
                sorted(map(tuple, np.split(index, np.cumsum(lengths)[:-1])))
            assert h.index.dtype == np.uint32 and h.index.max() <= top
            assert np.array_equal(np.sort(h.height), np.sort(height))
        assert st.xyz > st.full >= (st.sent if frame == 0 else 0)
        fresh = 2 * len(set(keys.tolist()) - set(prev.tolist())) if frame else 2 * len(keys)
        assert st.new_fans == fresh and (frame == 0 or st.sent < st.full * (fresh / (2 * len(keys)) + 0.05))
        prev = keys
        held_expected = held
    assert held_expected is not None
    assert decode_message(FanSender(1).encode([(np.zeros(0, np.int64), np.zeros(0, np.uint32), np.zeros(0, np.uint32),
                                                 np.zeros(0, np.float32))])[0])[0][1].size == 0


# -- roles ----------------------------------------------------------------------------------------
def test_roles_rank_map():
    roles = (Role("visualization", None), Role("computation", 3))
    assert assign_roles(roles, 5) == {"visualization": [0, 1], "computation": [2, 3, 4]}
    with pytest.raises(ConfigError, match="need 4 ranks"):
        assign_roles(roles, 3)
    with pytest.raises(ConfigError, match="exactly"):
        assign_roles((Role("server", 1), Role("client", 2)), 4)


def test_in_memory_table_equals_the_out_of_core_one(stores):
    from massview.data.terrain.roettger import table_from_grid
    from test_terrain_store import finest

    st = TerrainStore(stores["real"])
    a, b = compute_table(st, 3.0), table_from_grid(finest(st), 3.0)
    assert len(a) == len(b) == st.layout.n - 1 and all(np.array_equal(x, y) for x, y in zip(a, b))


@pytest.mark.parametrize("shape,C", [((760, 1000), 4), ((344, 403), 4), ((300, 237), 6), ((300, 237), 1)])
def test_paper_layout_follows_the_rule_and_covers(shape, C):
    from massview.systems.roettger_paper import paper_layout

    rows, cols = shape
    P, origins, D = paper_layout(rows, cols, C, 1025)
    m = int(np.log2(P - 1))
    if shape == (760, 1000):
        assert P == 513 and 2 ** (m - 1) + 1 < 1000 * 2 / C <= 2**m + 1  # the paper's own set-up
    covered = np.zeros(shape, bool)
    for oy, ox in origins:
        covered[oy: oy + P, ox: ox + P] = True
    assert covered.all() and len(origins) == C and D >= max(o + P for pair in origins for o in pair)


def test_bad_t2_options_fail_before_any_rank_starts(stores):
    proc = run_cli("render", stores["real"], "--system", "roettger", "--ranks", "3", "--compute-ranks", "2",
                   "--roettger-C", "1.5", "-q", check=False)
    assert proc.returncode != 0 and "[2, 64]" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli("render", stores["real"], "--system", "roettger", "--ranks", "2", "--compute-ranks", "2", "-q", check=False)
    assert proc.returncode != 0 and "no visualization rank" in proc.stderr
    proc = run_cli("render", stores["real"], "--system", "roettger", "--ranks", "4", "--compute-ranks", "2", "--wall", "1x1",
                   "-q", check=False)
    assert proc.returncode != 0 and "needs 1 visualization ranks" in proc.stderr


def test_fan_stream_without_delta_resends_everything():
    snd, rcv = FanSender(1), FanReceiver(1)
    keys = np.arange(5, dtype=np.int64) * 16
    lengths = np.full(5, 6, np.uint32)
    index = np.arange(30, dtype=np.uint32)
    for _ in range(2):
        msg, st = snd.encode([(keys, lengths, index, index.astype(np.float32))], delta=False)
        held = rcv.apply(np.frombuffer(msg, np.uint8))[0]
        assert st.new_fans == 5 and np.array_equal(held.index, index)


def test_children_only_propagation_would_break_the_level_rule(stores):
    """The checker above is not vacuous: Röttger's d2 propagated from children alone (not from
    the finer nodes touching a node from outside) leaves neighbouring leaves >= 2 levels apart."""
    from massview.data.terrain.roettger import k_factor, local_d2
    from massview.lod.roettger import select_leaves
    from test_terrain_store import finest

    st = TerrainStore(stores["real"])
    h, n = finest(st), st.layout.n
    K, d2, pushed = k_factor(2.0), [None] * (n - 1), None
    for t in range(n - 1, -1, -1):
        s = 2 ** (n - t - 1)
        cur = local_d2(h[::s, ::s], 2 * s)
        cur = cur if pushed is None else np.maximum(cur, pushed)
        if t < n - 1:
            d2[t] = cur
        f = cur * K
        pushed = np.maximum.reduce([f[0::2, 0::2], f[0::2, 1::2], f[1::2, 0::2], f[1::2, 1::2]]) if t else None
    w = (st.layout.S - 1) * 1.0
    worst = 0
    for eye in ((w / 2, -w / 2, 1500.0), (-0.05 * w, -0.4 * w, 1200.0), (0.3 * w, -0.35 * w, 1100.0)):
        for c in (0.3, 3.0, 30.0):
            lv = select_leaves(np.zeros((1, 2), np.int64), n, d2, eye, (1.0, 1.0), 1.0, (236.0, 1076.0),
                               RoettgerParams(C=2.0, c=c), (st.layout.S, st.layout.S))
            depth = np.zeros((2 ** n, 2 ** n), np.int64)
            for t in np.unique(lv.depth):
                sel = lv.depth == t
                g = np.full((2 ** int(t),) * 2, -1, np.int64)
                g[lv.row[sel], lv.col[sel]] = t
                g = np.repeat(np.repeat(g, 2 ** (n - int(t)), 0), 2 ** (n - int(t)), 1)
                depth = np.maximum(depth, g)
            worst = max(worst, np.abs(np.diff(depth, axis=0)).max(), np.abs(np.diff(depth, axis=1)).max())
    assert worst >= 2


def test_a_rank_holds_memory_in_proportion_to_its_portion(stores, monkeypatch):
    """Per-array accounting (the 16385² peak-RSS figure is `massview bench roettger --sections
    rss`): every array a computation rank keeps covers only its portion's box (+ the table's
    one-node halo), each store block is read once, and no more than one is alive at a time
    (a block cache held a second copy of the portion)."""
    import weakref

    info = dataclasses.replace(LayerInfo.of(stores["real"]), rows=513, cols=513)
    grid = info.S**2 * 4
    alive, reads, most = [0], [], [0]
    real_get = TerrainStore.get_block

    class Block(np.ndarray):
        pass

    def get_block(self, level, i, j):
        b = real_get(self, level, i, j).view(Block)
        alive[0] += 1
        weakref.finalize(b, lambda: alive.__setitem__(0, alive[0] - 1))
        reads.append((level, i, j))
        most[0] = max(most[0], alive[0])
        return b

    monkeypatch.setattr(TerrainStore, "get_block", get_block)
    for C in (4, 16):
        depth0 = partition_depth(C)
        for nodes in portion_nodes(depth0, C):
            reads.clear()
            part = LayerPortion(info, nodes, depth0)
            arrays = [part.heights] + [w.a for w in part.d2 if w is not None] + [w.a for w in (*part.zmin.values(), *part.zmax.values())]
            assert sum(a.nbytes for a in arrays) <= 1.2 * grid / C
            assert max(a.nbytes for a in arrays[1:]) <= 0.1 * part.heights.nbytes  # no table or range array of DEM size
            assert len(reads) == len(set(reads)) and len(reads) <= 9 * 16 // C  # each once: the portion's blocks (+ borders)
    assert most[0] <= 2, f"{most[0]} store blocks alive at once"


def test_bench_reads_layer_counts_and_pairs_each_frame_with_its_sequential_baseline():
    from massview.app.bench.roettger import parse_counts, per_frame

    assert parse_counts("1-3,6") == [1, 2, 3, 6] and parse_counts("4") == [4]
    with pytest.raises(ConfigError, match="--layers"):
        parse_counts("one")
    recs = [{"frame": f, "rank": r, "times_ms": {"total": 10.0 * (r + 1) + f, "lod": 5.0 * r},
             "counters": {"reference_lod_ms": 40.0, "reference_ms": 90.0} if r == 0 else {}} for f in (0, 1) for r in range(3)]
    fr = per_frame(recs, 1)
    assert fr[1] == {"par_lod": 10.0, "frame": 31.0, "seq_lod": 40.0, "seq": 90.0}


@pytest.mark.parametrize("opts", [[], ["--colormap", "viridis", "--exaggeration", "3", "--sun", "90,10", "--haze", "2"]])
def test_t2_draws_with_t1s_shading_options(terrain_store, tmp_path, opts):
    """T2 takes T1's --colormap, --exaggeration, --sun and --haze (it ignored all four: the
    frames were byte-identical with and without them, in its own brown ramp and no haze): the
    same store, camera and options give frames within ~1 level of T1's on average (the two LODs
    differ), and T2's parallel frame still equals its serial reference."""
    from conftest import load_png, run_cli, summary

    size = ["--frames", "1", "--size", "160x100", "-q"]
    run_cli("render", terrain_store, *opts, *size, "--out", tmp_path / "t1")
    run_cli("render", terrain_store, "--system", "roettger", "--ranks", "2", "--compute-ranks", "1", "--reference", *opts, *size,
            "--out", tmp_path / "t2")
    t1, t2 = (load_png(tmp_path / d / "frames" / "00000.png").astype(int) for d in ("t1", "t2"))
    assert np.abs(t1 - t2).mean() < 2.0
    assert summary(tmp_path / "t2")["max_abs_diff"] == 0
