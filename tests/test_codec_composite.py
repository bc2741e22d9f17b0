"""Codec round trips and the compositing algebra, as properties (no MPI needed)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from massview.core.camera import Viewport
from massview.core.image import Image, blank_image
from massview.parallel.codec import CODECS, decode_image, encode_image
from massview.parallel.composite import combine, radix_factors, split_rows
from massview.parallel.decompose import grid_shape, kd_tiles, sort_first_tiles


def random_image(rng, vp, fill):
    img = blank_image(vp)
    mask = rng.random((vp.h, vp.w)) < fill
    img.color[mask] = rng.integers(0, 256, (int(mask.sum()), 4), dtype=np.uint8)
    img.depth[mask] = rng.random(int(mask.sum())).astype(np.float32) * np.float32(0.999)
    return img


def same(a: Image, b: Image) -> bool:
    return a.viewport == b.viewport and np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)


@given(st.integers(0, 40), st.integers(0, 40), st.integers(0, 50), st.integers(0, 50),
       st.sampled_from([0.0, 1.0, 0.3, 0.97]), st.sampled_from(sorted(CODECS)), st.integers(0, 2**31))
@settings(max_examples=120, deadline=None)
def test_codec_round_trip(x, y, w, h, fill, codec, seed):
    img = random_image(np.random.default_rng(seed), Viewport(x, y, w, h), fill)
    assert same(decode_image(encode_image(img, codec)), img)


def test_codec_empty_image_is_tiny_and_full_image_round_trips():
    vp = Viewport(0, 0, 1280, 1024)
    assert len(encode_image(blank_image(vp))) < 200
    full = random_image(np.random.default_rng(1), vp, 1.0)
    assert same(decode_image(encode_image(full)), full)


@given(st.integers(0, 2**31), st.integers(1, 30), st.integers(1, 30))
@settings(max_examples=60, deadline=None)
def test_combine_is_associative_and_front_wins_ties(seed, w, h):
    rng = np.random.default_rng(seed)
    vp = Viewport(3, 5, w, h)
    a, b, c = (random_image(rng, vp, 0.6) for _ in range(3))
    # force some exact ties
    b.depth[::2] = a.depth[::2]
    assert same(combine(combine(a, b), c), combine(a, combine(b, c)))
    ab = combine(a, b)
    tie = (a.depth == b.depth)
    assert np.array_equal(ab.color[tie], a.color[tie])


def test_split_rows_covers_in_order():
    vp = Viewport(0, 7, 10, 5)
    bands = split_rows(vp, 8)
    assert sum(b.h for b in bands) == 5 and bands[0].y == 7
    assert all(bands[i].y + bands[i].h == bands[i + 1].y for i in range(7))


@pytest.mark.parametrize("n,k,expect", [(1, 4, []), (2, 2, [2]), (3, 2, [3]), (8, 4, [4, 2]), (12, 4, [4, 3]), (7, 4, [7])])
def test_radix_factors(n, k, expect):
    f = radix_factors(n, k)
    assert f == expect and int(np.prod(f)) == n


@pytest.mark.parametrize("layout", ["horizontal", "vertical", "grid", "kd"])
@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
def test_sort_first_tiles_partition_the_image(layout, n):
    rng = np.random.default_rng(n)
    rects = np.c_[rng.uniform(0, 600, (50, 2)), rng.uniform(0, 600, (50, 2))]
    rects = np.c_[np.minimum(rects[:, :2], rects[:, 2:]), np.maximum(rects[:, :2], rects[:, 2:])]
    tiles = sort_first_tiles(layout, n, 640, 480, rects=rects, weights=rng.uniform(1, 10, 50))
    cover = np.zeros((480, 640), int)
    for t in tiles:
        cover[t.slices()] += 1
    assert len(tiles) == n and np.all(cover == 1)


def test_kd_balances_weight():
    # all weight in the left quarter: the kd split must put most cuts there
    rects = np.array([[x, 0, x + 8, 480] for x in range(0, 160, 8)], float)
    tiles = kd_tiles(4, 640, 480, rects, np.ones(len(rects)))
    assert sum(t.x < 160 for t in tiles) >= 3


def test_grid_shape_prefers_square_tiles():
    assert grid_shape(4, 1280, 1024) == (2, 2)
    assert grid_shape(2, 1280, 720) == (1, 2)


@pytest.mark.parametrize("method", ["direct-send", "binary-swap", "radix-k"])
@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7])
def test_final_regions_partition_the_frame_in_row_bands(method, n):
    """What deliver learns without an allgather: the regions tile the frame, rows in order
    (parallel == serial renders in test_parallel_render check them against real compositing)."""
    from massview.parallel.composite import final_regions

    vp = Viewport(0, 0, 37, 29)
    regions = final_regions(n, method, 3, vp)
    assert len(regions) == n
    cover = np.zeros((vp.h, vp.w), int)
    for r in regions:
        cover[r.y:r.y + r.h, r.x:r.x + r.w] += 1
    assert (cover == 1).all()
    if method == "binary-swap" and n & (n - 1):
        p = 1 << (n.bit_length() - 1)
        assert all(regions[r].empty for r in range(1, 2 * (n - p), 2))  # folded ranks hold nothing


def test_launch_env_defaults_do_not_override_the_user():
    from massview.parallel.runtime import WAIT_ENV, launch_env, raster_threads

    assert raster_threads(2, cores=2) is None and raster_threads(4, cores=2) == 0
    env = launch_env(1 << 20, {"PATH": "/bin"})  # more ranks than any machine has cores
    assert all(env[k] == v for k, v in WAIT_ENV.items()) and env["LP_NUM_THREADS"] == "0"
    mine = launch_env(4, {"LP_NUM_THREADS": "3", "MPIR_CVAR_CH4_PROGRESS_THROTTLE": "0"})
    assert mine["LP_NUM_THREADS"] == "3" and mine["MPIR_CVAR_CH4_PROGRESS_THROTTLE"] == "0"


class _Comm:
    def __init__(self, size):
        self.size = size

    def Get_size(self):  # noqa: N802 - mpi4py's name
        return self.size


def test_auto_codec_picks_by_where_the_ranks_run():
    from massview.core.errors import ConfigError
    from massview.parallel.codec import all_ranks_local, resolve_codec

    assert all_ranks_local(_Comm(1), {}, 1)  # one rank: nothing travels
    assert all_ranks_local(_Comm(4), {"MPI_LOCALNRANKS": "4"}, 4)  # MPICH's Hydra, one node
    assert all_ranks_local(_Comm(2), {"OMPI_COMM_WORLD_LOCAL_SIZE": "4"}, 4)  # a sub-communicator of a one-node job
    assert not all_ranks_local(_Comm(8), {"MPI_LOCALNRANKS": "4"}, 8)  # two nodes of 4
    assert all_ranks_local(_Comm(4), {"SLURM_JOB_NUM_NODES": "1"}, 4)  # srun in a one-node allocation
    assert not all_ranks_local(_Comm(4), {"SLURM_JOB_NUM_NODES": "2"}, 4)
    assert not all_ranks_local(_Comm(4), {}, 4)  # unknown launcher: treated as spread over nodes
    assert resolve_codec(_Comm(1), "auto") == ("none", True)
    assert resolve_codec(_Comm(3), "lz4") == ("lz4", False)  # a named codec is used as it is, run-coded everywhere
    with pytest.raises(ConfigError, match="auto"):
        resolve_codec(_Comm(3), "zip")


def test_config_knows_every_codec_and_names_the_variable_of_a_bad_one():
    from massview.core.config import CODEC_NAMES, RenderConfig
    from massview.core.errors import ConfigError
    from massview.parallel.codec import CODEC_CHOICES

    assert CODEC_NAMES == CODEC_CHOICES
    with pytest.raises(ConfigError, match="MASSVIEW_CODEC"):
        RenderConfig.from_env({"MASSVIEW_CODEC": "zip"})
