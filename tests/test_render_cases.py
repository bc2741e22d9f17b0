"""The test helper that renders several cases in one job (conftest.render_cases): every case
writes its own outputs, and a failing case fails the job with an error naming that case, on one
rank (a plain process) and under real mpiexec (a rank's failure ends every rank)."""

import pytest

from conftest import SMALL_SCENE, load_png, render_cases, run_cli, summary

TINY = [SMALL_SCENE, "--frames", 1, "--size", "64x48"]


def test_one_rank_cases_equal_their_own_cli_runs_and_a_bad_case_is_named(tmp_path):
    outs = render_cases(tmp_path / "ok", 1, {"orbit": [*TINY, "--path", "orbit"], "turn": [*TINY, "--path", "turn"]})
    for name, out in outs.items():
        run_cli("render", *TINY, "--path", name, "--out", tmp_path / name, "-q")
        assert summary(out)["path"] == name and summary(out)["ranks"] == 1
        assert (load_png(out / "frames" / "00000.png") == load_png(tmp_path / name / "frames" / "00000.png")).all()
    assert not (load_png(outs["orbit"] / "frames" / "00000.png") == load_png(outs["turn"] / "frames" / "00000.png")).all()
    with pytest.raises(AssertionError, match="failed in case bad-one"):
        render_cases(tmp_path / "bad", 1, {"fine": TINY, "bad-one": [*TINY, "--decomposition", "no-such"], "never": TINY})
    assert (tmp_path / "bad" / "fine" / "summary.json").exists() and not (tmp_path / "bad" / "never").exists()


@pytest.mark.mpi
def test_a_failing_rank_ends_the_job_and_names_the_case(tmp_path):
    with pytest.raises(AssertionError, match=r"2-rank job of 3 render cases failed in case faulty(.|\n)*injected fault at frame 0"):
        render_cases(tmp_path, 2, {"fine": TINY, "faulty": [*TINY, "--fault", "1:0"], "never": TINY}, timeout=120)
    assert summary(tmp_path / "fine")["ranks"] == 2 and not (tmp_path / "never").exists()


@pytest.mark.mpi
def test_sort_first_tiles_without_pixels_render_nothing_and_still_equal_serial(tmp_path):
    """A 1×1 frame split among 3 sort-first ranks: two ranks get empty tiles. They draw nothing
    (their camera's projection divided by zero: ZeroDivisionError and MPI_Abort) and the
    assembled frame still equals the one-rank frame. Likewise a scene store's 2×2 frame in a
    3-tile grid (its per-tile selection took the empty tile's planes: ZeroDivisionError)."""
    scene = tmp_path / "c.scene"
    run_cli("generate", "scene", "city", "-o", scene, "--size", 0.01, "-q")
    cases = {dec: [SMALL_SCENE, "--frames", 2, "--size", "1x1", "--decomposition", dec, "--reference"]
             for dec in ("sort-first:kd", "sort-first:horizontal")}
    cases.update({f"scene-{dec}": [scene, "--frames", 2, "--size", "2x2", "--decomposition", dec, "--reference"]
                  for dec in ("sort-first:grid", "sort-first:vertical")})
    for dec, out in render_cases(tmp_path, 3, cases, timeout=180).items():
        s = summary(out)
        assert s["ranks"] == 3 and s["frames"] == 2 and s["max_abs_diff"] == 0, (dec, s)
