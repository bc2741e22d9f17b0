import json
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from massview.core.camera import Camera, Viewport
from massview.core.errors import ConfigError
from massview.core.paths import BUILTIN_PATHS, KeyframePath, load_path


def cam(**kw):
    return Camera.look_at((10.0, -20.0, 15.0), (0.0, 0.0, 0.0), width=640, height=480, near=0.5, far=200.0, **kw)


def test_look_at_points_at_target():
    c = cam()
    px, w = c.project(np.array([[0.0, 0.0, 0.0]]))
    assert np.allclose(px[0], [320, 240])
    assert w[0] > 0


@given(st.integers(0, 639), st.integers(0, 479), st.integers(1, 640), st.integers(1, 480))
@settings(max_examples=60, deadline=None)
def test_subfrustum_maps_its_pixels_to_the_whole_ndc_square(x, y, w, h):
    c = cam()
    w, h = min(w, 640 - x), min(h, 480 - y)
    vp = Viewport(x, y, w, h)
    rng = np.random.default_rng(x * 1000 + y)
    pts = rng.uniform(-5, 5, (20, 3))
    full = c.view_projection() @ np.c_[pts, np.ones(20)].T
    sub = c.view_projection(vp) @ np.c_[pts, np.ones(20)].T
    fx = (full[0] / full[3] + 1) / 2 * 640
    fy = (1 - full[1] / full[3]) / 2 * 480
    sx = (sub[0] / sub[3] + 1) / 2 * w + x
    sy = (1 - sub[1] / sub[3]) / 2 * h + y
    assert np.allclose(fx, sx, atol=1e-6) and np.allclose(fy, sy, atol=1e-6)
    assert np.allclose(full[2] / full[3], sub[2] / sub[3])  # same depth


def test_frustum_planes_classify_points():
    c = cam()
    planes = c.frustum_planes()
    inside = np.array([0.0, 0.0, 0.0, 1.0])
    behind = np.array([20.0, -40.0, 30.0, 1.0])
    assert np.all(planes @ inside >= 0)
    assert np.any(planes @ behind < 0)


def test_a_viewport_without_pixels_sees_nothing():
    """A sort-first tile of a frame smaller than its tiles has no pixels: its planes reject
    every point, sphere and box (they divided by zero: ZeroDivisionError on a scene store)."""
    from massview.lod.cull import boxes_in_frustum, spheres_in_frustum

    c = cam()
    pts = np.random.default_rng(1).uniform(-50, 50, (200, 3))
    for vp in (Viewport(0, 0, 0, 480), Viewport(640, 0, 0, 0), Viewport(3, 7, 5, 0)):
        planes = c.frustum_planes(vp)
        assert np.isfinite(planes).all()
        assert not np.any(np.all(np.c_[pts, np.ones(200)] @ planes.T >= 0, axis=1))
        assert not spheres_in_frustum(pts, np.full(200, 1e3), planes).any()
        assert not boxes_in_frustum(pts - 1e3, pts + 1e3, planes).any()
    assert np.all(c.frustum_planes() @ np.array([0.0, 0.0, 0.0, 1.0]) >= 0)


def test_camera_json_and_pickle_round_trip():
    c = cam(fovy=50)
    assert Camera.from_json(json.loads(json.dumps(c.to_json()))) == c
    assert pickle.loads(pickle.dumps(c)) == c


def test_camera_rejects_bad_values():
    with pytest.raises(ConfigError, match="near"):
        Camera((0, 0, 0), (1, 0, 0, 0), near=5, far=1)
    with pytest.raises(ConfigError, match="fovy"):
        Camera((0, 0, 0), (1, 0, 0, 0), fovy=180)


@pytest.mark.parametrize("end", [(0.5, 0, 6), (0, -0.5, 6), (-0.3, 0.4, 6)])
def test_a_path_through_the_nadir_keeps_its_roll(tmp_path, end):
    """walk6 #11: a keyframe straight above its target, then one beside it: the first frame's
    roll is the limit of the next ones' (it used to jump 90 degrees to world +y at the nadir)."""
    p = tmp_path / "up.json"
    p.write_text(json.dumps({"keyframes": [{"time": 0, "position": [0, 0, 6], "look_at": [0, 0, 0]},
                                           {"time": 1, "position": list(end), "look_at": [0, 0, 0]}]}))
    cams = load_path(str(p), [-1, -1, -1], [1, 1, 1]).cameras(4, 64, 48)
    assert np.allclose(cams[0].forward, [0, 0, -1])
    for a, b in zip(cams, cams[1:]):
        assert float(np.dot(a.right, b.right)) > 0.99 and float(np.dot(a.up, b.up)) > 0.99
    top = -np.array(end[:2]) / np.hypot(*end[:2])  # the image's top points from the eye over the target
    assert np.allclose(cams[0].up[:2], top, atol=1e-6)
    # looking straight down with nothing to follow: north up, east right (as before)
    still = Camera.look_at((0, 0, 6), (0, 0, 0))
    assert np.allclose(still.up, [0, 1, 0]) and np.allclose(still.right, [1, 0, 0])


@pytest.mark.parametrize("name", BUILTIN_PATHS)
def test_builtin_paths_fit_the_box_and_look_at_it(name):
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([100.0, 80.0, 10.0])
    cams = load_path(name, lo, hi).cameras(12, 320, 240)
    assert len(cams) == 12
    centers = np.array([[50.0, 40.0, 5.0]])
    for c in cams:
        assert c.near < c.far and np.all(np.isfinite(c.position))
    # over the path the scene is in view for most frames
    seen = [np.all(c.frustum_planes() @ np.r_[centers[0], 1.0] > -60) for c in cams]
    assert sum(seen) >= 6


def test_keyframes_pass_through_keys_and_reject_garbage(tmp_path):
    data = {"keyframes": [
        {"time": 0, "position": [0, 0, 10], "look_at": [10, 0, 0]},
        {"time": 1, "position": [10, 0, 10], "look_at": [20, 0, 0]},
        {"time": 3, "position": [10, 10, 12], "look_at": [10, 30, 0]},
    ]}
    p = tmp_path / "p.json"
    p.write_text(json.dumps(data))
    path = load_path(str(p), [0, 0, 0], [1, 1, 1])
    assert np.allclose(path.camera(0, 64, 48).position, [0, 0, 10])
    assert np.allclose(path.camera(1 / 3, 64, 48).position, [10, 0, 10])
    assert np.allclose(path.camera(1, 64, 48).position, [10, 10, 12])
    mid = path.camera(2 / 3, 64, 48).position
    assert 10 - 1 < mid[0] < 10 + 1 and 0 < mid[1] < 10
    bad = tmp_path / "bad.json"
    bad.write_text('{"keyframes": [{"time": 0}]}')
    with pytest.raises(ConfigError, match="bad.json"):
        load_path(str(bad), [0, 0, 0], [1, 1, 1])
    with pytest.raises(ConfigError, match="not valid JSON"):
        (tmp_path / "x.json").write_text("{")
        load_path(str(tmp_path / "x.json"), [0, 0, 0], [1, 1, 1])
    assert isinstance(path, KeyframePath)


@pytest.mark.parametrize("name", BUILTIN_PATHS)
def test_no_path_renders_the_same_view_twice(name):
    """The closed loops (turn, orbit) go once round in steps of 1/frames: their first and last
    views used to be the same full-circle position (a 2-frame orbit rendered one view twice);
    the open paths still start and end at their ends."""
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([100.0, 80.0, 20.0])
    for frames in (2, 3, 10):
        cams = load_path(name, lo, hi).cameras(frames, 64, 48)
        keys = {(tuple(np.round(c.position, 9)), tuple(np.round(c.orientation, 9))) for c in cams}
        assert len(keys) == frames, (name, frames)
    path = load_path(name, lo, hi)
    first, last = path.cameras(10, 64, 48)[0], path.cameras(10, 64, 48)[-1]
    assert np.allclose(first.position, path.camera(0.0, 64, 48).position)
    end = path.camera(0.9 if name in ("turn", "orbit") else 1.0, 64, 48)
    assert np.allclose(last.position, end.position) and np.allclose(last.orientation, end.orientation)


def test_reference_with_color_by_rank_is_refused_where_it_cannot_hold():
    """--reference asks for the one-rank image; --color-by-rank tints each rank's part: T1 and
    M1 can never pass that check (the README once suggested both together for M1), T2 tints its
    reference per portion and keeps both."""
    from massview.core.config import RenderConfig

    for system in ("auto", "dmmr"):
        with pytest.raises(ConfigError, match="drop one of them"):
            RenderConfig(reference=True, color_by_rank=True, system=system)
        RenderConfig(reference=True, system=system)
        RenderConfig(color_by_rank=True, system=system)
    RenderConfig(reference=True, color_by_rank=True, system="roettger")


@pytest.mark.parametrize("size", [(320, 240), (1280, 720), (240, 320), (1000, 100)])
@pytest.mark.parametrize("box", [((0, 0, 0), (100, 100, 20)), ((0, 0, 0), (400, 40, 10)), ((-5, -5, -5), (5, 5, 5))])
def test_orbit_keeps_the_whole_box_in_view_without_standing_far_off(size, box):
    """The default path: every corner of the scene's box inside the frame at every step (the
    near corners of a square terrain were cut off, more of a long scene), and one corner near
    the edge (the box fills the frame as far as its aspect allows); its near plane just before
    the box, so depth stays precise (far/near was ~20000: depth ties at a distant view made the
    forward and deferred draws differ in a pixel)."""
    lo, hi = np.array(box[0], float), np.array(box[1], float)
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for cam in load_path("orbit", lo, hi).cameras(12, *size):
        clip = corners @ cam.view_projection().T
        ndc = clip[:, :2] / clip[:, 3:4]
        assert (clip[:, 3] > 0).all() and np.abs(ndc).max() <= 1.0, (size, box, ndc)
        assert np.abs(ndc).max() >= 0.9, (size, box, ndc)
        depth = clip[:, 2] / clip[:, 3]  # inside the near and far planes, and the near plane not wastefully close
        assert np.abs(depth).max() <= 1.0 and cam.far / cam.near < 50, (size, box, depth, cam.near, cam.far)


@pytest.mark.parametrize("kf,extra,needle", [
    ({"position": [0, 0], "look_at": [1, 0, 0]}, {}, "keyframe 0: 'position' must be 3 finite numbers, got [0, 0]"),
    ({"position": [0, 0, float("nan")], "look_at": [1, 0, 0]}, {}, "keyframe 0: 'position' must be 3 finite numbers"),
    ({"position": [1, 2, 3], "look_at": [1, 2, 3]}, {}, "keyframe 0: 'look_at' equals 'position'"),
    ({"position": [1, 2, 3], "look_at": [0, 0, 0]}, {"fovy": 200}, "'fovy' must be a number of degrees between 0 and 180, got 200"),
])
def test_keyframe_file_errors_name_the_file_and_keyframe(tmp_path, kf, extra, needle):
    """Each of these named neither the file nor the keyframe (a Camera's message, or numpy's
    'inhomogeneous shape' for a 2-element position)."""
    import json

    from massview.core.errors import ConfigError
    from massview.core.paths import load_path

    f = tmp_path / "p.json"
    f.write_text(json.dumps({"keyframes": [{"time": 0, **kf}, {"time": 1, "position": [5, 5, 5], "look_at": [0, 0, 0]}], **extra}))
    with pytest.raises(ConfigError) as e:
        load_path(str(f), [0, 0, 0], [1, 1, 1]).cameras(2, 32, 24)
    assert str(f) in str(e.value) and needle in str(e.value)
