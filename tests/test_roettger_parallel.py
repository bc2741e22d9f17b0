"""T2 (Röttger) under real mpiexec with real renders: the parallel image equals the serial
whole-DEM reference for C = 1..4 computation ranks and 1-2 visualization ranks, with and
without a wall, on a DEM that is not 2^n+1; visualization ranks read 0 bytes of the store; a
tile that does not see a portion gets 0 bytes from its rank; the triangle budget holds; a
store's orthophoto is draped (the colour map ``auto``), parallel still equal to serial."""

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


class _Ortho(ArraySource):
    """An RGB orthophoto held in memory (``read_rgb``), as a GeoTIFF source gives it."""

    def __init__(self, rgb: np.ndarray):
        super().__init__(rgb[..., 0], "halves")
        self.rgb = rgb

    def read_rgb(self, r0, r1, c0, c1):
        return self.rgb[r0:r1, c0:c1]


@pytest.fixture(scope="module")
def ortho_store(tmp_path_factory):
    """The real DEM with an orthophoto: its west half red, its east half blue (stretched over the DEM)."""
    from test_roettger import real_dem

    dem = real_dem()
    rgb = np.zeros(dem.shape + (3,), np.uint8)
    half = dem.shape[1] // 2
    rgb[:, :half] = (220, 40, 40)
    rgb[:, half:] = (40, 40, 220)
    p = tmp_path_factory.mktemp("t2o") / "ortho.zarr"
    prepare_terrain(ArraySource(dem, "jacksboro", transform=(0.0, SPACING, 0.0, 0.0, 0.0, -SPACING)), p, block=129,
                    ortho=_Ortho(rgb))
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
def cases(tmp_path_factory, real_store, ortho_store):
    """The module's independent T2 renders: one job per rank count (conftest.RenderBatches).
    Looking straight down at col 226 (test_a_tile_that_does_not_see_a_portion_gets_zero_bytes)."""
    down = _top_down_path(real_store, tmp_path_factory.mktemp("t2path"), 226.0)
    return RenderBatches(tmp_path_factory, {
        **{f"parallel-{n}-{C}-{w}-{k}": (n, _args(real_store, C, "--reference", "--color-by-rank", *(["--wall", w] if w else []), layers=k))
           for n, C, w, k in PARALLEL},
        "zero-bytes": (6, _args(real_store, 4, "--decomposition", "sort-first:horizontal", frames=2, path=str(down))),
        "paper": (5, _args(real_store, 4, "--paper-partition", "--reference", frames=1)),
        "drape": (4, _args(ortho_store, 2, "--reference", "--haze", 0, frames=1, path="orbit")),
        "ramp": (3, _args(ortho_store, 2, "--colormap", "hypsometric", "--haze", 0, frames=1, path="orbit")),
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


def _red_blue(frame: np.ndarray) -> tuple[float, float]:
    """Fractions of the frame's pixels that are the orthophoto's red and blue, lit (the sky is
    light: red and green above 100)."""
    r, g, b = (frame[..., k].astype(np.int16) for k in range(3))
    red = (r > g + 40) & (r > b + 40) & (g < 100)
    blue = (b > r + 40) & (b > g + 40) & (r < 100)
    return float(red.mean()), float(blue.mean())


def test_the_orthophoto_is_draped_and_parallel_equals_serial(cases):
    # walk5 M2: T2 drew the height ramp on a store with an orthophoto (T1 drapes it), and
    # --colormap ortho drew grey. Now `auto` drapes it on both visualization ranks' tiles, the
    # image still equals the serial reference, and visualization ranks still read no store
    # (the computation leader reads the image and sends it).
    out = cases.out("drape")
    s, recs = _read(out)
    assert s["max_abs_diff"] == 0 and s["diff_fraction"] == 0.0, s
    red, blue = _red_blue(load_png(out / "frames" / "00000.png"))
    assert red > 0.05 and blue > 0.05, (red, blue)
    by_rank = defaultdict(int)
    for r in recs:
        by_rank[r["rank"]] += r["counters"].get("store_bytes_read", 0)
    assert by_rank[0] == by_rank[1] == 0 and by_rank[2] > by_rank[3] > 0  # rank 2 leads the computation ranks
    # An explicit colour map is the ramp, as before: no orthophoto colour in the frame.
    red, blue = _red_blue(load_png(cases.out("ramp") / "frames" / "00000.png"))
    assert blue < 0.001, blue
