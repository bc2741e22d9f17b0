"""The pipelined frame loop (issue 20) delivers the same images as the synchronous one."""

import numpy as np
import pytest

from conftest import SMALL_SCENE, SMALL_SIZE, load_png, run_cli, save_diff, summary

pytestmark = pytest.mark.mpi


def _render(out, scene, ranks, pipeline, decomposition, *extra, frames=3):
    run_cli("render", scene, "--ranks", ranks, "--decomposition", decomposition, "--frames", frames, "--size", SMALL_SIZE,
            "--out", out, "--pipeline", pipeline, "-q", *extra)
    return summary(out)


def _same_frames(a, b, frames):
    for f in range(frames):
        x, y = load_png(a / "frames" / f"{f:05d}.png"), load_png(b / "frames" / f"{f:05d}.png")
        if not np.array_equal(x, y):
            save_diff(x, y, a / f"diff{f}.png")
        assert np.array_equal(x, y), f"frame {f}: pipelined differs from synchronous; diff image in {a}"


@pytest.mark.parametrize("ranks,decomposition,extra", [
    (2, "sort-last", ("--compositor", "binary-swap")),
    (3, "sort-first:grid", ()),
    (4, "sort-last", ("--compositor", "radix-k", "--radix-k", "2")),
])
def test_pipelined_equals_synchronous(tmp_path, ranks, decomposition, extra):
    on = _render(tmp_path / "on", SMALL_SCENE, ranks, "on", decomposition, "--reference", *extra)
    off = _render(tmp_path / "off", SMALL_SCENE, ranks, "off", decomposition, *extra)
    _same_frames(tmp_path / "on", tmp_path / "off", 3)
    assert on["pipeline"] == "on" and off["pipeline"] == "off"
    assert on["max_abs_diff"] == 0 and on["frames"] == 3
    assert on["throughput_fps"] > 0 and on["latency_ms"] > 0


def test_pipelined_terrain_equals_synchronous(tmp_path, terrain_store):
    """Terrain: the next frame's LOD (with its residency Allreduce) runs beside compositing."""
    for mode in ("on", "off"):
        _render(tmp_path / mode, terrain_store, 2, mode, "sort-last:kpatch", "--loading", "complete", "--path", "flyover")
    _same_frames(tmp_path / "on", tmp_path / "off", 3)


def test_failure_in_a_pipelined_run_ends_every_rank(tmp_path):
    proc = run_cli("render", SMALL_SCENE, "--ranks", 3, "--frames", 4, "--size", SMALL_SIZE, "--out", tmp_path,
                   "-q", "--pipeline", "on", "--fault", "1:2", check=False, timeout=120)
    assert proc.returncode != 0
    assert proc.stderr.count("injected fault at frame 2") == 1, proc.stderr
