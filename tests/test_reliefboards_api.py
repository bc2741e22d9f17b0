"""M2 through the Python API: ``massview.render(..., system="reliefboards", ranks=N)`` runs the
real mpiexec job and returns the visualization rank's frames — equal, pixel for pixel, to the
CLI's frames of the same run. Board arrival is made deterministic for the comparison with
``wait_boards`` (``--wait-boards``): each frame first waits for every pending board, a mode
for comparisons only (M2 itself never waits)."""

import numpy as np
import pytest
from PIL import Image

import massview as mv
from conftest import run_cli
from massview.core.errors import ConfigError

SCENE = "builtin:objects?n=100"
OPTS = {"t_nz": 5000, "p": 32, "min_triangles": 100, "wait_boards": True}


@pytest.mark.mpi
def test_api_frames_equal_the_cli_frames(tmp_path):
    res = mv.render(SCENE, "forward", ranks=3, frames=6, size=(320, 240), system="reliefboards", reliefboards=OPTS)
    run_cli("render", SCENE, "--system", "reliefboards", "--ranks", 3, "--frames", 6, "--path", "forward", "--size", "320x240",
            "--tnz", 5000, "--board-px", 32, "--min-triangles", 100, "--wait-boards", "-q", "--out", tmp_path)
    assert len(res.images) == 6 and res.images[0].shape == (240, 320, 3)
    assert res.summary["system"] == "reliefboards" and res.summary["backends"] == 2
    c = [r["counters"] for r in res.stats]
    assert c[0]["boards_drawn"] == 0 and c[0]["requests"] > 0  # frame 0: nothing has arrived
    assert sum(k["boards_drawn"] > 0 for k in c[1:]) >= 3  # boards drawn: the frames depend on them
    assert all(k["far_original"] == 0 for k in c[1:])  # waiting: every far object has its board from frame 1 on
    assert res.summary["first_complete_frame"] is not None  # a frame with every far object drawn from a current board
    for f, img in enumerate(res.images):
        cli = np.asarray(Image.open(tmp_path / "frames" / f"{f:05d}.png").convert("RGB"))
        assert np.array_equal(img, cli), f"frame {f} differs"
    assert res.summary["board_passes_on_visualization_rank"] == 0


def test_api_refuses_one_rank_and_unknown_options():
    with pytest.raises(ConfigError, match="ranks=2"):
        mv.render(SCENE, "forward", ranks=1, frames=1, system="reliefboards")
    with pytest.raises(ConfigError, match="unknown option"):
        mv.render(SCENE, "forward", ranks=2, frames=1, system="reliefboards", reliefboards={"tnz": 5})
    with pytest.raises(ConfigError, match="depth"):
        mv.render(SCENE, "forward", ranks=2, frames=1, system="reliefboards", depth=True)


def test_settings_that_leave_no_board_to_draw_are_warned_before_the_run(tmp_path):
    """A run that cannot draw a board says so (the README's M2 examples ran whole runs with none:
    a small plant with no feasible cluster, and a 10-frame orbit turning 36° a frame, past E)."""
    from massview.core.paths import load_path
    from massview.systems.boardscene import open_board_objects
    from massview.systems.reliefboards_job import board_options, board_warnings

    opts = board_options(OPTS)
    objects = open_board_objects(SCENE, opts.cluster_params(240, 45.0))
    assert objects.feasible.sum() > 0

    def warned(path, frames):
        return board_warnings(objects, load_path(path, *objects.bounds).cameras(frames, 320, 240), opts.policy)

    assert len(warned("orbit", 10)) == 1 and "per frame about the feasible objects" in warned("orbit", 10)[0]
    assert warned("orbit", 60) == [] and warned("forward", 6) == []
    none = open_board_objects(SCENE, board_options({**OPTS, "min_triangles": 10**9}).cluster_params(240, 45.0))
    assert none.feasible.sum() == 0
    (w,) = board_warnings(none, None, opts.policy)
    assert "no object of this scene can get a board" in w
    proc = run_cli("render", SCENE, "--system", "reliefboards", "--ranks", 2, "--frames", 10, "--size", "160x120", "--tnz", 5000,
                   "--board-px", 32, "--min-triangles", 100, "--out", tmp_path)
    assert "massview: warning: the path moves" in proc.stderr
    assert len(__import__("json").loads((tmp_path / "summary.json").read_text())["warnings"]) == 1


@pytest.mark.mpi
def test_a_run_with_no_far_object_claims_no_complete_view():
    """walk6 #8: with every object inside the near zone, each frame counted as a "complete
    view" (no far object drawn as geometry) and the run said "complete view after 60 ms"
    although no board was ever drawn. A view with no far object proves nothing now."""
    from massview.app.reliefboards_cmds import summary_lines

    res = mv.render(SCENE, "forward", ranks=2, frames=2, size=(160, 120), system="reliefboards",
                    reliefboards={**OPTS, "t_nz": 10**8, "wait_boards": False})
    c = [r["counters"] for r in res.stats]
    assert all(k["far_objects"] == 0 and k["view_complete"] == 0 for k in c)
    s = res.summary
    assert s["frames_with_far_objects"] == 0 and s["first_complete_frame"] is None and s["ms_to_complete_view"] is None
    assert "no far object was in view in this run" in summary_lines(s)
