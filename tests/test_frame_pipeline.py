"""The pipelined frame loop (issue 20) delivers the same images as the synchronous one."""

import numpy as np
import pytest

from conftest import SMALL_SCENE, SMALL_SIZE, RenderBatches, load_png, run_cli, save_diff, summary

pytestmark = pytest.mark.mpi


def _args(scene, pipeline, decomposition, *extra, frames=3):
    return [scene, "--decomposition", decomposition, "--frames", frames, "--size", SMALL_SIZE, "--pipeline", pipeline, *extra]


def _same_frames(a, b, frames):
    for f in range(frames):
        x, y = load_png(a / "frames" / f"{f:05d}.png"), load_png(b / "frames" / f"{f:05d}.png")
        if not np.array_equal(x, y):
            save_diff(x, y, a / f"diff{f}.png")
        assert np.array_equal(x, y), f"frame {f}: pipelined differs from synchronous; diff image in {a}"


PAIRS = [
    (2, "sort-last", ("--compositor", "binary-swap")),
    (3, "sort-first:grid", ()),
    (4, "sort-last", ("--compositor", "radix-k", "--radix-k", "2")),
]


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """Both modes of every pair in one job per rank count (conftest.RenderBatches)."""
    return RenderBatches(tmp_path_factory, {
        **{f"{mode}-{ranks}": (ranks, _args(SMALL_SCENE, mode, d, *(("--reference",) if mode == "on" else ()), *extra))
           for ranks, d, extra in PAIRS for mode in ("on", "off")},
    }, label="pipeline")


@pytest.fixture(scope="module")
def terrain_cases(tmp_path_factory, terrain_store):
    return RenderBatches(tmp_path_factory, {
        mode: (2, _args(terrain_store, mode, "sort-last:kpatch", "--loading", "complete", "--path", "flyover")) for mode in ("on", "off")
    }, label="pipeline-terrain")


@pytest.mark.parametrize("ranks,decomposition,extra", PAIRS)
def test_pipelined_equals_synchronous(cases, ranks, decomposition, extra):
    on_dir, off_dir = cases.out(f"on-{ranks}"), cases.out(f"off-{ranks}")
    on, off = summary(on_dir), summary(off_dir)
    _same_frames(on_dir, off_dir, 3)
    assert on["pipeline"] == "on" and off["pipeline"] == "off"
    assert on["ranks"] == off["ranks"] == ranks and on["decomposition"] == off["decomposition"]
    assert on["decomposition"].startswith(decomposition)
    assert on["max_abs_diff"] == 0 and on["frames"] == 3
    assert on["throughput_fps"] > 0 and on["latency_ms"] > 0


def test_pipelined_terrain_equals_synchronous(terrain_cases):
    """Terrain: the next frame's LOD (with its residency Allreduce) runs beside compositing."""
    assert summary(terrain_cases.out("on"))["pipeline"] == "on" and summary(terrain_cases.out("off"))["pipeline"] == "off"
    _same_frames(terrain_cases.out("on"), terrain_cases.out("off"), 3)


def test_failure_in_a_pipelined_run_ends_every_rank(tmp_path):
    proc = run_cli("render", SMALL_SCENE, "--ranks", 3, "--frames", 4, "--size", SMALL_SIZE, "--out", tmp_path,
                   "-q", "--pipeline", "on", "--fault", "1:2", check=False, timeout=120)
    assert proc.returncode != 0
    assert proc.stderr.count("injected fault at frame 2") == 1, proc.stderr
