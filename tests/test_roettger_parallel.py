"""T2 (Röttger) under real mpiexec with real renders: the parallel image equals the serial
whole-DEM reference for C = 1..4 computation ranks and 1-2 visualization ranks, with and
without a wall, on a DEM that is not 2^n+1; visualization ranks read 0 bytes of the store; a
tile that does not see a portion gets 0 bytes from its rank; the triangle budget holds."""

import json
from collections import defaultdict

import numpy as np
import pytest

from conftest import RenderBatches, load_png, not_sky, run_cli, summary
from massview.core.image import BACKGROUND_RGBA
from massview.core.stats import read_stats
from massview.data.terrain import ArraySource, prepare_terrain
from massview.systems.roettger_portion import LayerInfo

pytestmark = pytest.mark.mpi

SIZE = "320x240"
SPACING = 80.0


@pytest.fixture(scope="module")
def real_store(tmp_path_factory):
    """The real 344 × 403 DEM (not 2^n+1), 80 m spacing, prepared by `prepare terrain` (with its table)."""
    from test_roettger import real_dem

    p = tmp_path_factory.mktemp("t2") / "real.zarr"
    prepare_terrain(ArraySource(real_dem(), "jacksboro", transform=(0.0, SPACING, 0.0, 0.0, 0.0, -SPACING)), p, block=129, color=None)
    return p


def _args(store, C, *extra, frames=2, path="zoom", layers=1):
    return [*[store] * layers, "--system", "roettger", "--compute-ranks", C, "--frames", frames, "--size", SIZE, "--path", path, *extra]


def _render(store, out, ranks, C, *extra, frames=2, path="zoom", layers=1):
    run_cli("render", *_args(store, C, *extra, frames=frames, path=path, layers=layers), "--ranks", ranks, "--out", out, "-q")
    return _read(out)


def _read(out):
    return summary(out), read_stats(out / "stats.jsonl")


PARALLEL = [(2, 1, None, 1), (4, 2, None, 1), (4, 3, None, 2), (6, 4, "2x1", 1), (4, 2, "1x2", 1)]


def _top_down_path(store, folder, col: float):
    info = LayerInfo.of(store)
    row = info.rows / 2
    z = info.zrange[1] + 60 * SPACING
    eye = [col * SPACING, -row * SPACING, z]
    tgt = [col * SPACING, -row * SPACING + 1.0, info.zrange[0]]
    path = folder / "down.json"
    path.write_text(json.dumps({"keyframes": [{"time": 0, "position": eye, "look_at": tgt},
                                              {"time": 1, "position": eye, "look_at": tgt}], "fovy": 45}))
    return path


@pytest.fixture(scope="module")
def cases(tmp_path_factory, real_store):
    """The module's independent T2 renders: one job per rank count (conftest.RenderBatches).
    Looking straight down at col 226 (test_a_tile_that_does_not_see_a_portion_gets_zero_bytes)."""
    down = _top_down_path(real_store, tmp_path_factory.mktemp("t2path"), 226.0)
    return RenderBatches(tmp_path_factory, {
        **{f"parallel-{n}-{C}-{w}-{k}": (n, _args(real_store, C, "--reference", "--color-by-rank", *(["--wall", w] if w else []), layers=k))
           for n, C, w, k in PARALLEL},
        "zero-bytes": (6, _args(real_store, 4, "--decomposition", "sort-first:horizontal", frames=2, path=str(down))),
        "paper": (5, _args(real_store, 4, "--paper-partition", "--reference", frames=1)),
    }, label="t2")


@pytest.mark.parametrize("ranks,C,wall,layers", PARALLEL)
def test_parallel_equals_serial_reference(cases, ranks, C, wall, layers):
    out = cases.out(f"parallel-{ranks}-{C}-{wall}-{layers}")
    s, recs = _read(out)
    assert s["ranks"] == ranks and s["wall"] == wall
    assert s["max_abs_diff"] == 0 and s["diff_fraction"] == 0.0, s
    nvis = ranks - C
    if wall:
        tiles = sorted((out / "wall").iterdir())
        assert len(tiles) == nvis
        frames = [load_png(t / "00001.png") for t in tiles]
    else:
        frames = [load_png(out / "frames" / "00001.png")]
    assert not any((f == BACKGROUND_RGBA[:3]).all(axis=2).any() for f in frames)  # the sky, not the clear colour
    drawn = sum(not_sky(f) for f in frames)
    assert drawn > 0.05 * sum(f.shape[0] * f.shape[1] for f in frames)  # the terrain is there
    by_rank = defaultdict(int)
    for r in recs:
        by_rank[r["rank"]] += r["counters"].get("store_bytes_read", 0)
    assert all(by_rank[v] == 0 for v in range(nvis))  # visualization ranks never read the store
    assert all(by_rank[c] > 0 for c in range(nvis, ranks))


def test_a_tile_that_does_not_see_a_portion_gets_zero_bytes(cases):
    # C = 4: the portions are the four quadrants of the padded 513² grid (cols < 256: ranks 0, 2
    # of the computation ranks). Looking straight down at col 226, the left tile sees only
    # cols < 226; the right tile sees both halves.
    _, recs = _read(cases.out("zero-bytes"))
    sent = defaultdict(int)
    for r in recs:
        if r["rank"] >= 2:
            for v in (0, 1):
                sent[(r["rank"] - 2, v)] += r["counters"].get(f"bytes_to_vis_{v}", 0)
    assert sent[(1, 0)] == 0 and sent[(3, 0)] == 0  # right quadrants → left tile: nothing
    assert sent[(1, 1)] > 0 and sent[(0, 0)] > 0 and sent[(0, 1)] > 0
    second = [r for r in recs if r["frame"] == 1 and r["rank"] >= 2]
    assert all(r["counters"]["new_fans"] == 0 for r in second)  # a still camera: nothing new is sent
    assert sum(r["bytes_sent"] for r in second) < 0.05 * sum(r["counters"]["bytes_full"] for r in second)


def test_triangle_budget_holds_on_every_frame(real_store, tmp_path):
    _, free = _render(real_store, tmp_path / "free", 3, 2, frames=3, path="orbit")
    per_frame = defaultdict(int)
    for r in free:
        per_frame[r["frame"]] += r["counters"].get("fan_triangles", 0)
    budget = int(0.5 * min(per_frame.values()))
    _, recs = _render(real_store, tmp_path / "budget", 3, 2, "--triangle-budget", budget, frames=3, path="orbit")
    got, drawn = defaultdict(int), {}
    for r in recs:
        if r["rank"] >= 1:
            got[r["frame"]] += r["counters"]["fan_triangles"]
            assert "budget_unreachable" not in r["counters"]
        else:
            drawn[r["frame"]] = r["counters"]["drawn_triangles"]
            assert r["triangles"] == 0  # counted once, by the computation ranks
    assert len(got) == 3
    for f, n in got.items():
        assert 0.9 * budget <= n <= budget, (f, n, budget)
        assert drawn[f] == n  # one visualization rank draws exactly what was agreed


def test_paper_partition_renders_with_overlapping_portions(cases):
    out = cases.out("paper")
    s, recs = _read(out)
    assert s["frames"] == 1 and "max_abs_diff" in s  # reported; the paper's seams are allowed
    frame = load_png(out / "frames" / "00000.png")
    assert not_sky(frame) > 0.05 * frame.shape[0] * frame.shape[1]
    assert all(r["counters"]["store_bytes_read"] > 0 for r in recs if r["rank"] >= 1)
