"""Offline renders are final quality, and keyframe files fit their clip planes to the scene."""

import json
import re
import subprocess

import numpy as np
import pytest

import massview as mv
from conftest import load_png, run_cli, summary
from massview.core.paths import load_path


def terrain_fraction(depth: np.ndarray) -> float:
    """Pixels with terrain in them (the sky behind the terrain is painted at the far plane)."""
    return float(np.mean(depth < 1.0))


def test_default_render_has_no_frame_with_missing_terrain(tmp_path, terrain_store):
    run_cli("render", terrain_store, "--path", "zoom", "--frames", 4, "--size", "320x240", "--out", tmp_path, "-q")
    recs = [json.loads(x) for x in (tmp_path / "stats.jsonl").read_text().splitlines()]
    assert len(recs) == 4
    assert all(r["counters"]["deferred_splits"] == 0 for r in recs)  # every split the view wants was drawn
    # each frame equals its camera rendered after a warm-up render of the same view (all its data resident)
    scene = mv.open_scene(terrain_store)
    cams = mv.path("zoom", scene, frames=4, size=(320, 240))
    for f in range(4):
        res = mv.render(scene, [cams[f], cams[f]], depth=True)
        warm = res.images[1]
        got = load_png(tmp_path / "frames" / f"{f:05d}.png")
        assert terrain_fraction(res.depths[1]) > 0.2 and np.array_equal(got, warm), f"frame {f} is not final quality"
    scene.close()
    assert summary(tmp_path)["frames"] == 4


def _walk_store(d, name: str, seed: int, relief: float, spacing: float):
    """A 257² random-walk terrain ``relief`` metres high, samples ``spacing`` metres apart,
    prepared into ``d/<name>.zarr``."""
    a = np.random.default_rng(seed).normal(0, 1, (257, 257)).cumsum(0).cumsum(1).astype(np.float32)
    a = (a - a.min()) / (a.max() - a.min()) * relief
    np.save(d / f"{name}.npy", a)
    run_cli("prepare", "terrain", d / f"{name}.npy", "-o", d / f"{name}.zarr", "--spacing", spacing, "-q")
    return d / f"{name}.zarr"


@pytest.fixture(scope="module")
def large_scene(tmp_path_factory):
    """A 100+ km terrain: 257² samples 500 m apart."""
    return _walk_store(tmp_path_factory.mktemp("large"), "big", 2, 3000, 500)


def _keyframes(path, extra=None):
    data = {"keyframes": [{"time": 0, "position": [-20000, 20000, 15000], "look_at": [64000, -64000, 0]},
                          {"time": 1, "position": [-15000, 15000, 14000], "look_at": [64000, -64000, 0]}], **(extra or {})}
    path.write_text(json.dumps(data))
    return path


def test_keyframes_without_clip_planes_do_not_clip_a_large_scene(tmp_path, large_scene):
    scene = mv.open_scene(large_scene)
    lo, hi = scene.bounds
    assert np.linalg.norm(hi - lo) > 100_000
    fitted = load_path(str(_keyframes(tmp_path / "k.json")), lo, hi)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    reach = max(np.linalg.norm(corners - p, axis=1).max() for p in fitted.positions)
    assert fitted.far > reach and fitted.near < 0.01 * reach
    _, img = mv.render_frame(scene, str(tmp_path / "k.json"), size=(240, 180), depth=True)
    with pytest.warns(mv.MassviewWarning, match="does not look at the scene"):  # (its far plane ends short of the terrain)
        _, old = mv.render_frame(scene, str(_keyframes(tmp_path / "old.json", {"near": 0.1, "far": 10000})), size=(240, 180), depth=True)
    assert terrain_fraction(img) > 0.3 and terrain_fraction(img) > 3 * terrain_fraction(old)
    explicit = load_path(str(_keyframes(tmp_path / "e.json", {"near": 2.0, "far": 5e5})), lo, hi)
    assert explicit.clip() == (2.0, 5e5)  # given clip planes are kept
    scene.close()


def test_a_far_back_orbit_still_shows_the_terrain_through_the_haze(terrain_store, tmp_path):
    """The orbit fitted to a tall, narrow frame stands ~50 terrain diagonals away; haze measured
    from the eye ("30 % across the diagonal") then faded the whole terrain into the sky (0 pixels
    unlike the sky at 100x4000). Haze now starts one diagonal short of the terrain's box: the
    terrain shows, and frames whose eye is within a diagonal of it (every default path, the
    recorded draws in test_terrain_draw) are unchanged."""
    from conftest import load_png, not_sky, run_cli

    run_cli("render", terrain_store, "--frames", 1, "--size=60x1200", "--out", tmp_path, "-q")
    f = load_png(tmp_path / "frames" / "00000.png")
    assert not_sky(f) > 500, "the terrain faded into the sky"


def test_sort_last_linear_splits_the_terrain_into_slabs(terrain_store, tmp_path):
    """sort-last:linear assigns each patch by the origin x of the finest M-block under it (the
    paper's §4.1.1 slabs): by the block a patch draws from, every patch of a coarse block (origin
    x = 0) went to rank 0 — [46848, 0, 1024, 0] triangles at 4 ranks on the demo's orbit. Every
    rank now draws a slab, and the frame still equals the serial one."""
    from conftest import run_cli, summary

    run_cli("render", terrain_store, "--ranks", 4, "--decomposition", "sort-last:linear", "--frames", 1, "--size", "160x100",
            "--reference", "--out", tmp_path, "-q")
    s = summary(tmp_path)
    assert s["max_abs_diff"] == 0
    tri = s["triangles_per_rank"]
    assert min(tri) > 0.1 * max(tri), tri


@pytest.fixture(scope="module")
def steep_scene(tmp_path_factory):
    """A terrain whose relief is ~6 % of its extent (a real mountain DEM's ratio): 1 km of relief
    over 257² samples 60 m apart."""
    return _walk_store(tmp_path_factory.mktemp("steep"), "steep", 5, 1000, 60)


@pytest.mark.parametrize("name", ["flyover", "turn", "forward", "zoom"])
def test_built_in_paths_fly_over_the_exaggerated_relief(tmp_path, steep_scene, name):
    """The built-in paths are fitted to the terrain as drawn at the render's exaggeration: at 10×
    every camera is above the exaggerated top and the first frame shows terrain (it was all sky,
    or the terrain's underside, with the paths fitted to the 1× box), through the API and the CLI
    alike."""
    scene = mv.open_scene(steep_scene)
    lo, hi = scene.bounds
    top10 = lo[2] + 10 * (hi[2] - lo[2])
    cams = mv.path(name, scene, frames=3, size=(160, 120), exaggeration=10)
    assert all(c.position[2] > top10 for c in cams)
    res = mv.render(scene, cams[:1], exaggeration=10, depth=True)
    assert terrain_fraction(res.depths[0]) > 0.05 and res.summary["triangles_per_frame"] > 0
    scene.close()
    run_cli("render", steep_scene, "--path", name, "--frames", 1, "--size", "160x120", "--exaggeration", 10, "--out", tmp_path, "-q")
    assert np.array_equal(load_png(tmp_path / "frames" / "00000.png"), res.images[0])


def test_cameras_that_see_nothing_and_ineffective_colour_options_are_warned(tmp_path, steep_scene):
    """Keyframes in a terrain's CRS coordinates (far off its world box) render sky only: the run
    says so and names the box; a camera that sees the terrain, and the built-in paths, get no
    such warning. --colormap ortho on a store without an orthophoto and a washing-out --haze
    are warned too (walk5 H3, M3, M8)."""
    kf = tmp_path / "utm.json"
    kf.write_text(json.dumps({"keyframes": [{"time": 0, "position": [345000, 5135000, 6000], "look_at": [372500, 5135000, 1000]},
                                            {"time": 1, "position": [346000, 5135000, 6000], "look_at": [372500, 5135000, 1000]}]}))
    proc = run_cli("render", steep_scene, "--path", kf, "--frames", 2, "--size", "64x48", "--out", tmp_path / "a", "-q")
    assert "none of the 2 cameras looks at the scene (x 0..15360, y -15360..0, z 0..1000; world metres" in proc.stderr
    assert summary(tmp_path / "a")["triangles_per_frame"] == 0
    proc = run_cli("render", steep_scene, "--path", "orbit", "--frames", 2, "--size", "64x48", "--out", tmp_path / "b", "-q",
                   "--colormap", "ortho", "--haze", 10)
    assert "looks at the scene" not in proc.stderr and "look at the scene" not in proc.stderr
    assert "--colormap ortho draws grey terrain here" in proc.stderr and "has no orthophoto" in proc.stderr
    assert "--haze 10 hides most of the terrain" in proc.stderr
    s = mv.open_scene(steep_scene)
    with pytest.warns(mv.MassviewWarning, match="the camera does not look at the scene"):
        mv.render(s, mv.camera(s, position=(7000, -7000, 3000), look_at=(7000, -7000, 9000), size=(64, 48)))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", mv.MassviewWarning)
        mv.render(s, mv.camera(s, position=(7000, -7000, 3000), look_at=(7000, -7000, 0), size=(64, 48)))
    s.close()


def test_keyframe_files_that_show_nothing_useful_are_warned_or_named(tmp_path, steep_scene):
    """Keyframes all at one time render keyframe 0 every frame (a still): warned. A camera under
    the terrain's lowest point inside its extent: warned. A keyframe without 'look_at' is named
    in one sentence that mentions 'orientation' (walk5 M5, L1)."""
    def kf(name, frames):
        p = tmp_path / f"{name}.json"
        p.write_text(json.dumps({"keyframes": frames}))
        return p

    same = kf("same", [{"time": 0, "position": [7000, -7000, 3000], "look_at": [7000, -6000, 0]},
                       {"time": 0, "position": [8000, -7000, 3000], "look_at": [8000, -6000, 0]}])
    proc = run_cli("render", steep_scene, "--path", same, "--frames", 2, "--size", "64x48", "--out", tmp_path / "a", "-q")
    assert "all 2 keyframes have time 0: every frame shows keyframe 0" in proc.stderr
    one = kf("one", [{"time": 0, "position": [7000, -7000, 3000], "look_at": [7000, -6000, 0]}])  # (walk6 #10)
    proc = run_cli("render", steep_scene, "--path", one, "--frames", 2, "--size", "64x48", "--out", tmp_path / "o", "-q")
    assert "one keyframe, so all 2 frames show it (a still)" in proc.stderr
    under = kf("under", [{"time": 0, "position": [7000, -7000, -500], "look_at": [9000, -7000, -300]}])
    proc = run_cli("render", steep_scene, "--path", under, "--frames", 1, "--size", "64x48", "--out", tmp_path / "b", "-q")
    assert "camera 0 is 500 m below the terrain's lowest point" in proc.stderr
    good = kf("good", [{"time": 0, "position": [7000, -7000, 3000], "look_at": [7000, -6000, 0]},
                       {"time": 1, "position": [8000, -7000, 3000], "look_at": [8000, -6000, 0]}])
    proc = run_cli("render", steep_scene, "--path", good, "--frames", 2, "--size", "64x48", "--out", tmp_path / "c", "-q")
    assert "warning" not in proc.stderr
    nolook = kf("nolook", [{"time": 0, "position": [7000, -7000, 3000], "look_at": [7000, -6000, 0]},
                           {"time": 1, "position": [8000, -7000, 3000]}])
    proc = run_cli("render", steep_scene, "--path", nolook, "--frames", 2, "--size", "64x48", "--out", tmp_path / "d", "-q", check=False)
    assert proc.returncode != 0 and "keyframe 1 has no 'look_at' [x, y, z] (or give every keyframe an 'orientation'" in proc.stderr
    assert proc.stderr.count("nolook.json") == 1 and "Traceback" not in proc.stderr


def test_render_video_has_every_frame_and_a_later_run_removes_a_stale_one(tmp_path, steep_scene):
    """``render --video`` writes OUT/video.mp4 with one video frame per rendered frame (walk5
    M7: only the demo wrote a video); a later run into the same folder without --video removes
    it with the other outputs of the earlier run, so no video of old frames stays beside new ones."""
    import imageio_ffmpeg

    run_cli("render", steep_scene, "--path", "flyover", "--frames", 5, "--size", "96x64", "--video", "--out", tmp_path, "-q")
    assert imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "video.mp4"))[0] == 5
    run_cli("render", steep_scene, "--path", "orbit", "--frames", 2, "--size", "96x64", "--out", tmp_path, "-q")
    assert not (tmp_path / "video.mp4").exists() and len(list((tmp_path / "frames").glob("*.png"))) == 2


def test_a_video_keeps_the_frames_size_and_pixels(tmp_path, capfd):
    """walk7 L3: a 641x361 run's video came out 648x368, stretched by ffmpeg's scaler, with
    imageio's raw warning. Now it is the frames' size (an odd side one row or column more, a
    copy of the last: yuv420p needs even sizes), pixel for pixel up to H.264's loss."""
    import imageio_ffmpeg
    from PIL import Image

    from massview.app.demo import write_video

    (tmp_path / "f").mkdir()
    yy, xx = np.mgrid[0:37, 0:65]
    frames = [np.stack([(xx * 4 + 20 * k) % 256, yy * 6, np.full_like(xx, 128)], -1).astype(np.uint8) for k in range(3)]
    for k, f in enumerate(frames):
        Image.fromarray(f).save(tmp_path / "f" / f"{k:05d}.png")
    write_video(tmp_path / "f", tmp_path / "v.mp4")
    probe = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-i", str(tmp_path / "v.mp4")], capture_output=True, text=True)
    assert re.search(r"Video: h264.*, 66x38", probe.stderr), probe.stderr[-1500:]
    raw = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(tmp_path / "v.mp4"), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], capture_output=True, check=True).stdout
    got = np.frombuffer(raw, np.uint8).reshape(-1, 38, 66, 3)
    assert len(got) == 3
    for g, f in zip(got, frames):
        assert np.abs(g[:37, :65].astype(int) - f).mean() < 6  # (H.264 loss only: not shifted or stretched)
    assert "resizing" not in capfd.readouterr().err
