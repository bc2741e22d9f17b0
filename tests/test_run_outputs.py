"""A run into an output folder that already holds a run: the old run's frames, stats and
summary are removed first (a 2-frame run after a 5-frame one used to leave frames 2–4 of the
old run beside the new ones, and the demo's video was mostly the old run), and nothing else
in the folder is touched."""

from __future__ import annotations

import json

from massview.core.stats import clear_run_outputs
from conftest import SMALL_SCENE, SMALL_SIZE, run_cli


def test_clear_run_outputs_removes_only_a_runs_files(tmp_path):
    made = ["summary.json", "stats.jsonl", "report.png", "video.mp4", "frames/00000.png", "frames/00004.png", "depth/00001.npy",
            "wall/r0c1/00002.png", "wall_depth/r1c0/00003.npy"]
    kept = ["notes.txt", "frames/cover.png", "frames/0001.png", "wall/readme.txt", "mine/00000.png", "wall/other/00000.png",
            "demo.mp4"]
    for rel in made + kept:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"x")
    assert clear_run_outputs(tmp_path) == len(made)
    assert not any((tmp_path / rel).exists() for rel in made)
    assert all((tmp_path / rel).exists() for rel in kept)
    gone = ["depth", "wall_depth/r1c0", "wall_depth", "wall/r0c1"]  # emptied: removed (a depth-less run left an empty depth/)
    assert not any((tmp_path / d).exists() for d in gone) and (tmp_path / "frames").is_dir() and (tmp_path / "wall").is_dir()
    assert clear_run_outputs(tmp_path) == 0  # (nothing left to remove; a missing folder is no error)
    assert clear_run_outputs(tmp_path / "none") == 0


def test_a_shorter_render_into_the_same_folder_leaves_only_its_own_frames(tmp_path):
    out = tmp_path / "run"
    (out / "frames").mkdir(parents=True)
    (out / "frames" / "keep-me.txt").write_text("a user's file")
    run_cli("render", SMALL_SCENE, "--frames", 4, "--size", SMALL_SIZE, "--out", out, "-q")
    assert sorted(p.name for p in (out / "frames").glob("*.png")) == [f"{i:05d}.png" for i in range(4)]
    run_cli("render", SMALL_SCENE, "--frames", 2, "--size", "160x120", "--out", out, "-q")
    assert sorted(p.name for p in (out / "frames").glob("*.png")) == ["00000.png", "00001.png"]
    assert json.loads((out / "summary.json").read_text())["frames"] == 2
    assert len((out / "stats.jsonl").read_text().splitlines()) == 2
    assert (out / "frames" / "keep-me.txt").read_text() == "a user's file"


def test_the_summary_names_the_split_m1_makes(tmp_path):
    """M1's server divides the frustum itself: the summary (and progress line) said
    "sort-last, binary-swap", the defaults it never used."""
    out = tmp_path / "m1"
    run_cli("render", "builtin:objects?n=200", "--system", "dmmr", "--ranks", 2, "--frames", 1, "--size", "96x72", "--out", out, "-q")
    s = json.loads((out / "summary.json").read_text())
    assert (s["decomposition"], s["compositor"]) == ("sort-first:balanced", "sub-frame assembly")


def test_a_gpu_budget_too_small_for_one_block_is_refused_before_the_earlier_run_is_cleared(tmp_path, terrain_store):
    """walk7 M1: ``--gpu-mb 1`` on a 257-block store was refused by the GL pool, after the earlier
    run's frames and summary in the same --out had been removed; it is a check of the options
    now, made before anything is touched."""
    out = tmp_path / "keep"
    run_cli("render", terrain_store, "--frames", 2, "--size", "160x120", "--out", out, "-q")
    before = sorted(p.name for p in out.rglob("*"))
    bad = run_cli("render", terrain_store, "--frames", 2, "--size", "160x120", "--gpu-mb", 1, "--out", out, "-q", check=False)
    assert bad.returncode != 0 and "--gpu-mb 1" in bad.stderr and "raise --gpu-mb" in bad.stderr
    assert sorted(p.name for p in out.rglob("*")) == before and json.loads((out / "summary.json").read_text())["frames"] == 2
