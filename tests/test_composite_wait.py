"""The sleeping wait (``MASSVIEW_MPI_WAIT=sleep``, parallel/exchange.py) under real mpiexec:
every compositor at 3 and 4 ranks gives the serial fold bit for bit, and a real sort-last
render gives the same image in both wait modes and equals the serial one; bad values fail
with an error naming the variable; the launcher picks sleep only when ranks outnumber cores."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import SMALL_SCENE, SMALL_SIZE, RenderBatches, clean_env, load_png

pytestmark = pytest.mark.mpi


@pytest.mark.parametrize("ranks", [3, 4])
def test_sleep_wait_composites_equal_the_serial_fold(ranks):
    mpiexec = str(Path(sys.executable).parent / "mpiexec")
    job = Path(__file__).parent / "composite_job.py"
    proc = subprocess.run([mpiexec, "-n", str(ranks), sys.executable, str(job), "1500"], capture_output=True, text=True,
                          env=clean_env(MASSVIEW_MPI_WAIT="sleep"), timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "composite job ok" in proc.stdout


WAIT_CASES = [(3, "binary-swap"), (3, "direct-send"), (4, "radix-k"), (4, "binary-swap")]


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """Per wait mode (the job's MASSVIEW_MPI_WAIT), the sort-last renders of WAIT_CASES in one
    job per rank count (conftest.RenderBatches)."""
    renders = {f"{c}-{n}": (n, [SMALL_SCENE, "--decomposition", "sort-last", "--compositor", c, "--frames", 2, "--size", SMALL_SIZE,
                                "--reference"]) for n, c in WAIT_CASES}
    return {mode: RenderBatches(tmp_path_factory, renders, env={"MASSVIEW_MPI_WAIT": mode}, label=f"wait-{mode}")
            for mode in ("poll", "sleep")}


@pytest.mark.parametrize("ranks,compositor", WAIT_CASES)
def test_render_is_the_same_in_both_wait_modes(cases, ranks, compositor):
    outs = {mode: cases[mode].out(f"{compositor}-{ranks}") for mode in ("poll", "sleep")}
    for out in outs.values():
        s = json.loads((out / "summary.json").read_text())
        assert s["ranks"] == ranks and s["compositor"] == compositor
        assert s["max_abs_diff"] == 0 and s["diff_fraction"] == 0.0
    frames = sorted(p.name for p in (outs["poll"] / "frames").glob("*.png"))
    assert len(frames) == 2
    for name in frames:
        a, b = (load_png(outs[mode] / "frames" / name) for mode in ("poll", "sleep"))
        assert np.array_equal(a, b), name


def test_bad_wait_mode_names_the_variable(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "massview", "render", SMALL_SCENE, "--ranks", "2", "--frames", "1", "--size", SMALL_SIZE,
                           "--out", str(tmp_path), "-q"], capture_output=True, text=True, env=clean_env(MASSVIEW_MPI_WAIT="nap"), timeout=300)
    assert proc.returncode != 0
    assert "MASSVIEW_MPI_WAIT='nap'" in proc.stderr and "poll, sleep" in proc.stderr and "Traceback" not in proc.stderr


def test_set_wait_mode_checks_and_returns_the_previous_mode():
    from massview.core.errors import ConfigError
    from massview.parallel import exchange

    before = exchange.set_wait_mode("sleep")
    try:
        assert exchange.wait_mode() == "sleep"
        with pytest.raises(ConfigError, match="use one of poll, sleep"):
            exchange.set_wait_mode("spin")
        assert exchange.set_wait_mode("poll") == "sleep"
    finally:
        exchange.set_wait_mode(before)


def test_launcher_sleeps_only_when_ranks_outnumber_cores():
    from massview.parallel.runtime import launch_env

    assert launch_env(3, {}, cores=2)["MASSVIEW_MPI_WAIT"] == "sleep"
    assert "MASSVIEW_MPI_WAIT" not in launch_env(2, {}, cores=2)
    assert launch_env(4, {"MASSVIEW_MPI_WAIT": "poll"}, cores=2)["MASSVIEW_MPI_WAIT"] == "poll"


def test_bench_rejects_an_unknown_wait_mode():
    from massview.app.bench.composite import parse_modes
    from massview.core.errors import ConfigError

    assert parse_modes("poll, sleep") == ["poll", "sleep"]
    with pytest.raises(ConfigError, match="--wait"):
        parse_modes("poll,yield")


def test_bench_rejects_an_unknown_codec():
    from massview.app.bench.composite import parse_codecs
    from massview.core.errors import ConfigError

    assert parse_codecs("auto, blosc2") == ["auto", "blosc2"]
    with pytest.raises(ConfigError, match="--codec"):
        parse_codecs("auto,zip")


def test_bench_composite_marks_the_default_wait_and_says_what_the_floor_is(tmp_path):
    """walk12: the table could not be read without the README — which wait mode render uses,
    what the floor is, what the target is. One small real run (2 ranks, both modes)."""
    from conftest import run_cli

    from massview.app.bench.composite import default_wait

    out = run_cli("bench", "composite", "--ranks", "2", "--size", "96x64", "--repeat", "1", "--json", tmp_path / "r.json").stdout
    flat = " ".join(out.split())
    assert "floor = the bytes a rank receives ÷ the point-to-point bandwidth" in flat and "within 3×" in flat
    assert f"{default_wait(2)} *" in out and "* = the wait mode render uses" in flat
    assert (tmp_path / "r.json").exists()
