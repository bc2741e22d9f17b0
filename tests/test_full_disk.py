"""walk9 M1, M2: a disk that fills up. Every writer ends in one line naming the file and what to
do (not a traceback), the prepare continues after space is freed, and a video ffmpeg could not
finish is an error and is removed instead of a broken file reported as written. On a real
tmpfs (root may mount one; skipped where mounting is not permitted)."""

from __future__ import annotations

import os
import subprocess
from contextlib import contextmanager

import numpy as np
import pytest

from conftest import run_cli
from massview.data.generators import synthetic_heights


@contextmanager
def _small_disk(path, size: str):
    path.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _remount(path, size: str):
    subprocess.run(["mount", "-o", f"remount,size={size}", str(path)], check=True)


def _one_error_line(proc):
    lines = [ln for ln in proc.stderr.strip().splitlines() if "_tiffWriteProc" not in ln]  # (GDAL's own log lines)
    assert proc.returncode in (1, 2) and len(lines) == 1 and "no space left on the device" in lines[0], proc.stderr
    return lines[0]


def test_prepare_terrain_on_a_full_disk_says_what_it_kept_and_continues(tmp_path):
    np.save(tmp_path / "d.npy", synthetic_heights(0, 600, 0, 600, 600, 3))
    with _small_disk(tmp_path / "disk", "1200k") as disk:
        out = disk / "s.zarr"
        proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", out, "--block", "129", "-q", check=False)
        line = _one_error_line(proc)
        assert line.startswith("massview: error: no space left on the device writing ") and str(out) in line and "free space, then:" in line and "the same command" in line
        _remount(disk, "64m")
        proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", out, "--block", "129", "-q")
        assert ("resumed" in proc.stdout or "started" in proc.stdout) and run_cli("verify", out, "-q").returncode == 0


def test_generate_scene_and_render_on_a_full_disk_are_one_line(tmp_path):
    with _small_disk(tmp_path / "disk", "200k") as disk:
        _one_error_line(run_cli("generate", "scene", "plant", "--size", "0.05", "-o", disk / "p.zarr", "-q", check=False))
        _one_error_line(run_cli("generate", "terrain", "-o", disk / "t.tif", "--size", "1025", "-q", check=False))  # (GDAL's error)
        assert not (disk / "t.tif.partial").exists() and not (disk / "t.tif").exists()
        _one_error_line(run_cli("render", "builtin:objects", "--frames", "4", "--size", "320x240", "--out", disk / "r",
                                "-q", check=False))


def test_a_video_ffmpeg_cannot_finish_is_an_error_and_is_removed(tmp_path):
    from PIL import Image

    from massview.app.demo import _whole_mp4, write_video
    from massview.core.errors import OutputError

    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for i in range(12):  # noise: an MP4 of some size
        Image.fromarray(rng.integers(0, 255, (96, 128, 3), dtype=np.uint8)).save(frames / f"{i:05d}.png")
    good = write_video(frames, tmp_path / "v.mp4")
    assert _whole_mp4(good)
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    assert not _whole_mp4(cut)
    with _small_disk(tmp_path / "disk", "64k") as disk:
        (disk / "filler").write_bytes(b"\0" * (64 * 1024 - 12 * 1024))
        with pytest.raises(OutputError, match="could not write the video .* the frames are in"):
            write_video(frames, disk / "video.mp4")
        assert not (disk / "video.mp4").exists()
