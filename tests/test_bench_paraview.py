"""``massview bench paraview``'s equal-triangle comparison: which ParaView surfaces bracket
massview's triangle count, and ParaView's frame time interpolated to it (never extrapolated).
The pure functions are tested here; one test runs ``pvbatch`` when it is installed (it is
never a dependency) and checks the surface sizes the bracketing assumes."""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
import shutil
import stat

import numpy as np
import pytest

from massview.app.bench.paraview import auto_steps, bracket_steps, interpolate_ms, run_pvbatch, surface_triangles, x_display
from massview.core.errors import ConfigError


def test_surface_triangles_match_the_readme_surfaces():
    assert surface_triangles(4097, 4097, 1) == 2 * 4096 * 4096  # full: 33.55 M
    assert surface_triangles(4097, 4097, 2) == 2 * 2048 * 2048  # every 2nd: 8.39 M
    assert surface_triangles(4097, 4097, 10) == 2 * 409 * 409  # every 10th: 0.33 M (samples 0..4090)
    assert surface_triangles(100, 50, 7) == 2 * 14 * 7
    with pytest.raises(ConfigError, match="--steps"):
        surface_triangles(10, 10, 0)


@pytest.mark.parametrize("rows,cols", [(4097, 4097), (1000, 700), (65, 129)])
def test_bracket_steps_are_adjacent_and_bracket(rows, cols):
    full = surface_triangles(rows, cols, 1)
    for tri in np.unique(np.geomspace(3, full - 1, 60).astype(int)):
        steps = bracket_steps(rows, cols, float(tri))
        counts = [surface_triangles(rows, cols, s) for s in steps]
        if len(steps) == 1:
            assert counts[0] == tri
        else:
            assert steps[1] == steps[0] + 1 and counts[0] > tri > counts[1]


def test_bracket_steps_exact_and_missing_bracket():
    assert bracket_steps(4097, 4097, surface_triangles(4097, 4097, 10)) == [10]
    assert bracket_steps(4097, 4097, 370_000) == [9, 10]  # 0.414 M and 0.335 M
    assert bracket_steps(65, 65, 1e9) == [1]  # more than the full surface: no bracket
    with pytest.raises(ConfigError, match="triangles"):
        bracket_steps(65, 65, 0)


def test_auto_steps_cover_every_count():
    grid = {"rows": 4097, "cols": 4097}
    assert auto_steps(grid, [370_000, 380_000, 500_000]) == [8, 9, 10]
    with pytest.raises(ConfigError, match="--skip-massview"):
        auto_steps(grid, [])


def test_interpolate_ms_is_linear_inside_and_none_outside():
    pts = [(334_562.0, 70.0), (414_050.0, 80.0), (8_388_608.0, 900.0)]
    assert interpolate_ms(pts, 334_562) == 70.0
    assert interpolate_ms(pts, (334_562 + 414_050) / 2) == pytest.approx(75.0)
    assert interpolate_ms(pts, 414_050 + 0.25 * (8_388_608 - 414_050)) == pytest.approx(285.0)
    assert interpolate_ms(pts, 300_000) is None  # below the smallest surface: never extrapolated
    assert interpolate_ms(pts, 9e6) is None
    assert interpolate_ms([(5.0, 1.0)], 5.0) == 1.0
    assert interpolate_ms([], 5.0) is None


@pytest.mark.skipif(shutil.which("pvbatch") is None or (shutil.which("Xvfb") is None and not os.environ.get("DISPLAY")),
                    reason="pvbatch/Xvfb not installed (Debian: apt-get install paraview xvfb)")
def test_pvbatch_surfaces_have_the_bracketed_triangle_counts(tmp_path):
    """Real pvbatch on one rank: its surface of every STEP-th sample has surface_triangles()."""
    rows, cols = 41, 57
    raw = tmp_path / "g.heights.raw"
    (np.random.default_rng(0).random((rows, cols)) * 10).astype(np.float32).tofile(raw)
    grid = {"raw": str(raw), "rows": rows, "cols": cols, "dx": 1.0, "dy": 1.0, "vscale": 1.0}
    cams = tmp_path / "cams.json"
    cams.write_text(json.dumps({"size": [64, 48], "cameras": [
        {"position": [28.0, -20.0, 80.0], "focal": [28.0, -20.0, 0.0], "up": [0.0, 1.0, 0.0], "fovy": 45.0}]}))
    for step in (1, 3):
        out = run_pvbatch(grid, cams, step, 1, tmp_path)
        assert out["triangles"] == surface_triangles(rows, cols, step)
        assert len(out["seconds"]) == 1 and out["seconds"][0] > 0


def test_massview_jobs_are_launched_with_arguments_bench_frame_accepts(monkeypatch, tmp_path):
    """bench paraview runs massview's frames through bench frame's job launcher: every argument
    that launcher passes must exist on the namespace bench paraview builds (a missing one broke
    the whole comparison once) and parse as a real ``bench frame`` command line. The MPI launch
    itself is replaced: this test is about the code around it."""
    from types import SimpleNamespace

    from massview.app.bench import frame, paraview
    from massview.app.cli import build_parser

    launched = []

    def fake_relaunch(argv, n):
        launched.append((argv, n))
        ns = build_parser().parse_args(argv)
        ns.worker.write_text(json.dumps({"ranks": n, "codec": ns.codec, "decomposition": ns.decomposition}))
        return 0

    monkeypatch.setattr(frame, "relaunch", fake_relaunch)
    out = paraview._massview(SimpleNamespace(size="320x240", frames=2), tmp_path / "store.zarr", [1, 2])
    assert len(launched) == 4 and {k for k in out} == {("sort-last", 1), ("sort-last", 2), ("sort-first", 1), ("sort-first", 2)}
    assert all(v["codec"] == "auto" for v in out.values())


def test_x_display_uses_the_callers_display_and_starts_nothing(monkeypatch):
    monkeypatch.setenv("DISPLAY", ":42")
    monkeypatch.setattr("subprocess.Popen", lambda *a, **k: pytest.fail("started a server although DISPLAY is set"))
    with x_display() as d:
        assert d == ":42"


def test_x_display_without_display_or_xvfb_says_what_to_install(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr(shutil, "which", lambda name, *a, **k: None)
    with pytest.raises(RuntimeError, match="apt-get install xvfb"), x_display():
        pass


def test_x_display_reports_an_xvfb_that_does_not_start(monkeypatch, tmp_path):
    fake = tmp_path / "Xvfb"
    fake.write_text("#!/bin/sh\necho '(EE) cannot establish any listening sockets' >&2\nexit 1\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setenv("PATH", f"{tmp_path}{os.pathsep}{os.environ.get('PATH', '')}")
    with pytest.raises(RuntimeError, match="did not start.*cannot establish"), x_display(timeout=10):
        pass


@pytest.mark.skipif(shutil.which("Xvfb") is None or ctypes.util.find_library("X11") is None,
                    reason="Xvfb/libX11 not installed (Debian: apt-get install xvfb)")
def test_x_display_starts_one_real_server_and_stops_it(monkeypatch):
    """A real Xvfb: a client connects to the display it reports, and none can once the block ends."""
    monkeypatch.delenv("DISPLAY", raising=False)
    x11 = ctypes.CDLL(ctypes.util.find_library("X11"))
    x11.XOpenDisplay.restype, x11.XOpenDisplay.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
    x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
    with x_display() as d:
        assert d.startswith(":") and d[1:].isdigit()
        conn = x11.XOpenDisplay(d.encode())
        assert conn
        x11.XCloseDisplay(conn)
    assert not x11.XOpenDisplay(d.encode())
