"""``massview report DIR`` on real render outputs, whole and damaged: a last stats line cut short
(a run killed while writing) is left out with a note, a broken summary.json is recomputed, a bad
line before the last is an error naming it; one-frame runs and M2 runs get a meaningful table
and plot (a new user's second walkthrough found a traceback, empty plots and '1 rank' for M2)."""

import json
import shutil

import numpy as np
import pytest

from conftest import run_cli


@pytest.fixture(scope="module")
def run2(tmp_path_factory):
    out = tmp_path_factory.mktemp("rep") / "run"
    run_cli("render", "builtin:objects?n=60", "--ranks", 2, "--frames", 3, "--size", "160x120", "--out", out, "-q")
    return out


def _copy(run2, tmp_path):
    d = tmp_path / "run"
    shutil.copytree(run2, d)
    return d


def test_report_of_a_whole_run(run2, tmp_path):
    d = _copy(run2, tmp_path)
    proc = run_cli("report", d)
    assert "ranks" in proc.stdout and (d / "report.png").stat().st_size > 10_000
    assert "note" not in proc.stderr


def test_a_last_line_cut_short_is_left_out_with_a_note(run2, tmp_path):
    d = _copy(run2, tmp_path)
    data = (d / "stats.jsonl").read_bytes()
    (d / "stats.jsonl").write_bytes(data[:-60])  # the last record cut in the middle
    (d / "summary.json").write_text('{"scene": "x", "fr')  # and the summary never finished
    proc = run_cli("report", d)
    assert "is cut short" in proc.stderr and "left out" in proc.stderr
    assert "summary.json does not parse" in proc.stderr
    assert "Traceback" not in proc.stderr and (d / "report.png").exists()


def test_a_damaged_line_before_the_last_is_named(run2, tmp_path):
    d = _copy(run2, tmp_path)
    lines = (d / "stats.jsonl").read_text().splitlines()
    lines[1] = lines[1][:40]
    (d / "stats.jsonl").write_text("\n".join(lines) + "\n")
    proc = run_cli("report", d, check=False)
    assert proc.returncode != 0 and "line 2 is not a frame record" in proc.stderr and "Traceback" not in proc.stderr


def test_one_frame_report(tmp_path):
    """A one-frame run's report is written (its points are drawn as markers: a line of one point
    drew nothing before; looked at, not asserted)."""
    out = tmp_path / "one"
    run_cli("render", "builtin:objects?n=60", "--ranks", 2, "--frames", 1, "--size", "160x120", "--out", out, "-q")
    run_cli("report", out)
    assert (out / "report.png").stat().st_size > 10_000


def test_m2_summary_table():
    from rich.console import Console

    from massview.app.report import print_summary

    s = {"system": "reliefboards", "scene": "forest.zarr", "frames": 40, "size": [640, 480], "backends": 2, "mean_frame_ms": 61.0,
         "frame_ms_p99": 207.1, "objects": 13, "feasible": 4, "requests": 80, "answered": 78, "loads_per_backend": [40, 40],
         "response_ms": {"count": 78, "min": 166.7, "median": 387.2, "max": 715.9}, "angle_error_deg": {"count": 0},
         "ms_to_complete_view": None, "ranks": 1, "imbalance": 1.0, "bytes_per_frame": 0, "warnings": ["the path moves 36°"]}
    con = Console(record=True, width=200)
    print_summary(s, con)
    text = con.export_text()
    assert "3 (1 visualization + 2 backends)" in text and "median 387.2 ms" in text and "not reached in this run" in text
    assert "imbalance" not in text and "bytes_per_frame" not in text and "the path moves 36°" in text
    json.dumps(s)


def test_an_interrupted_run_is_reported_as_interrupted(run2, tmp_path):
    """No summary.json and 2 of 3 frames in stats.jsonl (a run stopped by Ctrl-C): the table was
    printed as if the run were complete."""
    d = _copy(run2, tmp_path)
    (d / "summary.json").unlink()
    lines = (d / "stats.jsonl").read_text().splitlines()
    (d / "stats.jsonl").write_text("\n".join(line for line in lines if '"frame": 2' not in line) + "\n")
    proc = run_cli("report", d)
    assert "the run was interrupted after 2 frames" in proc.stderr, proc.stderr
    assert "interrupted after 2 frames" in proc.stdout and (d / "report.png").exists()


def test_dmmr_clients_are_plotted_by_what_they_did(tmp_path):
    """M1's client records have no frame time (total 0: the server's frame period is the frame
    time); the report plotted them as 0 ms. Now each client's line is the sum of its stages."""
    from massview.app.report import load_run, rank_times

    out = tmp_path / "dm"
    run_cli("render", "builtin:objects?n=60", "--system", "dmmr", "--ranks", 2, "--frames", 2, "--size", "160x120", "--out", out, "-q")
    _, records = load_run(out)
    frames, ranks, ms, busy, _ = rank_times(records)
    assert ranks == [0, 1] and busy.tolist() == [False, True]
    client = [r for r in records if r["rank"] == 1]
    assert all(r["times_ms"]["total"] == 0 for r in client)
    assert (ms[:, 1] > 0).all() and np.allclose(ms[:, 1], [sum(v for k, v in r["times_ms"].items() if not k.startswith("vis_"))
                                                         for r in sorted(client, key=lambda r: r["frame"])])
    run_cli("report", out)
    assert (out / "report.png").stat().st_size > 10_000
