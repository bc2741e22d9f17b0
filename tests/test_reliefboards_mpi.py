"""M2 under real mpiexec: boards come from the backends only, every request is answered by a
replica holder, and a stalled backend delays only its own requests, not the frames."""

import json

import numpy as np
import pytest

from conftest import run_cli, summary

SCENE = "builtin:objects?n=100"
M2 = ["--system", "reliefboards", "--size", "320x240", "--tnz", 5000, "--board-px", 32, "--min-triangles", 100, "-q"]


def _records(out):
    return [json.loads(line) for line in (out / "stats.jsonl").read_text().splitlines()]


@pytest.mark.mpi
def test_boards_come_from_backends_and_replace_far_originals(tmp_path):
    out = tmp_path / "m2"
    run_cli("render", SCENE, "--ranks", 3, "--frames", 16, "--path", "forward", "--reference", "--out", out, *M2)
    s = summary(out)
    assert s["backends"] == 2 and s["feasible"] > 5
    assert s["board_passes_on_visualization_rank"] == 0  # the visualization rank built no board
    built = sum(b["built"] for b in s["backend_counters"])
    assert built == s["answered"] + s["late_boards"] > 0
    assert s["requests"] == s["answered"] + s["pending_at_end"]
    assert s["tris_board_mean"] > 0 and s["angle_error_deg"]["count"] > 0
    assert s["angle_error_deg"]["max"] < 45.0  # never a board past E
    recs = _records(out)
    assert all(len(r["counters"]["pending_by_backend"]) == 2 for r in recs)
    # (whether some frame is complete, every far object drawn from a current board, depends on how
    # far the backends lag: a loaded CI machine had none in 16 frames; test_api_frames_equal_the_cli_frames
    # asserts it with --wait-boards)
    assert s["boards_drawn"] > 0
    assert 0 < s["diff_fraction"] < 0.2  # boards differ from all-original geometry, but little
    assert (out / "frames" / "00015.png").exists()


@pytest.mark.mpi
def test_a_stalled_backend_delays_only_its_own_requests(tmp_path):
    common = ["--ranks", 3, "--frames", 20, "--path", "turn", "--replicas", 1, *M2]
    ref, stalled = tmp_path / "ref", tmp_path / "stalled"
    run_cli("render", SCENE, *common, "--out", ref)
    run_cli("render", SCENE, *common, "--stall-backend", 2, "--out", stalled)
    a, b = summary(ref), summary(stalled)
    stuck = next(c for c in b["backend_counters"] if c["rank"] == 2)
    fine = next(c for c in b["backend_counters"] if c["rank"] == 1)
    assert stuck["built"] == 0 and stuck["received"] > 0  # it held every request it got
    recs = _records(stalled)
    assert recs[-1]["counters"]["pending_by_backend"][1] == stuck["received"]  # all its requests still wait ...
    # ... while the other backend answered all but (at most) those issued in the last frames before STOP
    recent = sum(r["counters"]["loads"][0] for r in recs[-3:])
    assert fine["built"] > 0 and fine["unserved"] <= recent
    assert b["answered"] == fine["built"] - b["late_boards"]
    # the frame loop never waited for it: the stalled backend answers nothing until STOP, so a
    # visualization rank that waited would never finish frame 1; all 20 frames are there. (The p99
    # frame times, stalled against not, are figures for the benchmark, not a wall-clock test.)
    assert b["frames"] == a["frames"] == 20
    assert np.isfinite(b["frame_ms_p99"]) and np.isfinite(a["frame_ms_p99"])


def test_one_rank_is_refused_with_a_clear_message(tmp_path):
    proc = run_cli("render", SCENE, "--frames", 1, "--out", tmp_path, *M2, check=False)
    assert proc.returncode != 0 and "--ranks 2" in proc.stderr


@pytest.mark.mpi
def test_stalling_a_rank_that_is_no_backend_is_refused(tmp_path):
    proc = run_cli("render", SCENE, "--ranks", 2, "--frames", 1, "--stall-backend", 5, "--out", tmp_path, *M2, check=False)
    assert proc.returncode != 0 and "--stall-backend 5 is not a backend rank" in proc.stderr
