"""The demo end to end (small terrain, few frames): every promised file, and a summary printed."""

import json

import pytest

from conftest import run_cli

pytestmark = pytest.mark.mpi


def test_demo_leaves_frames_video_stats_summary_report(tmp_path):
    out = tmp_path / "demo"
    proc = run_cli("demo", "--frames", 6, "--terrain-size", 1025, "--cache-dir", tmp_path / "cache", "--out", out, timeout=600)
    assert len(list((out / "frames").glob("*.png"))) == 6
    video = out / "demo.mp4"
    assert video.stat().st_size > 1000 and video.read_bytes()[4:8] == b"ftyp"  # an MP4 container
    s = json.loads((out / "summary.json").read_text())
    assert s["ranks"] == 2 and s["decomposition"] == "sort-last:kpatch" and s["size"] == [1280, 720]
    assert len((out / "stats.jsonl").read_text().splitlines()) == 12
    assert (out / "report.png").stat().st_size > 10000
    assert "triangles per frame" in proc.stdout and "imbalance" in proc.stdout and str(video) in proc.stdout
    # the terrain is cached: a second run does not generate it again
    again = run_cli("demo", "--frames", 2, "--terrain-size", 1025, "--cache-dir", tmp_path / "cache", "--out", out, timeout=600)
    assert "using the cached demo terrain" in again.stderr
