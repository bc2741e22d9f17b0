"""Reliefboards (§5) on real GL: creation view, silhouette, 10° off-axis against a flat billboard,
relighting; the grid mesh and the wire codec."""

import math

import numpy as np
import pytest

from massview.core.camera import Camera
from massview.core.errors import CorruptBlockError
from massview.data.generators import generate_objects
from massview.lod.reliefboard import Reliefboard, board_frame, decode_board, encode_board, grid_triangles

gl = pytest.importorskip("massview.render.boards")
from massview.render.context import create_context  # noqa: E402
from massview.render.framebuffer import Framebuffer  # noqa: E402
from massview.render.meshes import MeshRenderer  # noqa: E402

W = H = 160


def _object(scene, i):
    a, b = scene.index_offset[i], scene.index_offset[i + 1]
    idx = scene.indices[a:b]
    used = np.unique(idx)
    remap = np.full(int(idx.max()) + 1, -1, np.int64)
    remap[used] = np.arange(len(used))
    return scene.positions[used], scene.normals[used], scene.colors[used], remap[idx].astype("u4")


@pytest.fixture(scope="module")
def setup():
    ctx = create_context()
    mesh = _object(generate_objects(6, 3), 0)  # a superquadric of ~3k triangles
    lo, hi = mesh[0].min(0), mesh[0].max(0)
    centre, r = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    dist = 40 * r  # far and narrow: perspective close to the board's orthographic capture
    fovy = 2 * math.degrees(math.atan(1.2 * r / dist))

    def camera(deg):
        a = math.radians(deg)
        d = np.array([math.cos(a), math.sin(a), 0.3])
        d /= np.linalg.norm(d)
        return Camera.look_at(centre + d * dist, centre, fovy=fovy, near=dist - 3 * r, far=dist + 3 * r, width=W, height=H)

    size = int(round(r * H / (dist * math.tan(math.radians(fovy) / 2))))  # projected diameter (px)
    builder = gl.BoardBuilder(ctx)
    cam0 = camera(30)
    board = builder.build(0, *mesh, direction=cam0.forward, size=size)
    original = MeshRenderer(ctx, *mesh, [0, len(mesh[3])])
    fb = Framebuffer(ctx, W, H)

    def render(draw, cam):
        fb.begin()
        draw(cam.view_projection())
        ctx.finish()
        return fb.read(cam.viewport)

    yield dict(ctx=ctx, board=board, builder=builder, original=original, camera=camera, render=render, size=size)
    original.release()
    builder.release()
    fb.release()


def _boards(ctx, board):
    relief, flat = gl.BoardRenderer(ctx), gl.BoardRenderer(ctx)
    relief.put(board)
    flat.put(board, flat=True)
    return relief, flat


def _grow(m):
    """Mask dilated by one pixel (8-neighbourhood)."""
    out = m.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out |= np.roll(np.roll(m, dy, 0), dx, 1)
    return out


def _diff(a, b):
    return np.abs(a.color[..., :3].astype(np.int32) - b.color[..., :3])


def test_four_passes_and_a_vertex_per_covered_pixel(setup):
    b = setup["board"]
    assert setup["builder"].passes_run == 4
    assert b.frame.size == setup["size"] and b.stencil.shape == (b.frame.size,) * 2
    assert b.vertex_count == int(b.stencil.sum()) > 1000
    assert np.all((b.distance >= 0) & (b.distance <= 2 * b.frame.radius))


def test_board_from_its_creation_direction_equals_the_original(setup):
    relief, _ = _boards(setup["ctx"], setup["board"])
    cam = setup["camera"](30)
    o = setup["render"](lambda m: setup["original"].draw(np.array([0]), m), cam)
    b = setup["render"](lambda m: relief.draw([0], m), cam)
    mo, mb = o.depth < 1, b.depth < 1
    # silhouette: the grid's vertices sit at pixel centres, so at most a one-pixel rim differs
    band = _grow(mo) & _grow(~mo)
    bad = (mo ^ mb) & ~band
    assert not np.any(bad), "silhouette differs away from the one-pixel rim"
    assert (mo ^ mb).sum() < 0.05 * mo.sum()
    d = _diff(o, b)[mo & mb]
    assert d.mean() < 1.5 and np.percentile(d, 99) <= 6
    relief.release()


def test_ten_degrees_off_axis_closer_than_a_flat_billboard(setup):
    relief, flat = _boards(setup["ctx"], setup["board"])
    cam = setup["camera"](40)
    o = setup["render"](lambda m: setup["original"].draw(np.array([0]), m), cam)
    b = setup["render"](lambda m: relief.draw([0], m), cam)
    f = setup["render"](lambda m: flat.draw([0], m), cam)
    err_board, err_flat = _diff(o, b).mean(), _diff(o, f).mean()
    sil_board = ((o.depth < 1) ^ (b.depth < 1)).sum()
    sil_flat = ((o.depth < 1) ^ (f.depth < 1)).sum()
    assert err_board < 0.6 * err_flat and sil_board < sil_flat
    relief.release()
    flat.release()


def test_relit_board_matches_the_relit_original(setup):
    relief, _ = _boards(setup["ctx"], setup["board"])
    light = np.array([-0.8, 0.3, 0.5])
    relief.set_light(light)
    orig = setup["original"]
    before = orig.prog["u_light"].value
    orig.prog["u_light"].value = tuple(light / np.linalg.norm(light))
    cam = setup["camera"](30)
    try:
        o = setup["render"](lambda m: orig.draw(np.array([0]), m), cam)
        b = setup["render"](lambda m: relief.draw([0], m), cam)
    finally:
        orig.prog["u_light"].value = before
    both = (o.depth < 1) & (b.depth < 1)
    d = _diff(o, b)[both]
    assert d.mean() < 1.5 and np.percentile(d, 99) <= 6
    # and the light really changed the picture
    o_default = setup["render"](lambda m: orig.draw(np.array([0]), m), cam)
    assert _diff(o, o_default)[both].mean() > 10
    relief.release()


def test_grid_mesh_is_cut_where_the_stencil_is_empty():
    s = np.array([[1, 1, 0], [1, 1, 1], [0, 1, 1]], bool)
    tris = grid_triangles(s).reshape(-1, 3)
    assert len(tris) == 2 + 1 + 1 + 2  # two full blocks, two three-pixel blocks
    assert tris.max() == s.sum() - 1
    assert len(grid_triangles(np.eye(4, dtype=bool))) == 0  # a diagonal line has no area


def test_wire_codec_round_trip_and_size():
    rng = np.random.default_rng(5)
    frame = board_frame([0, 0, 0], [2, 1, 3], [1.0, 2.0, -0.5], 37)
    stencil = rng.random((37, 37)) < 0.6
    n = int(stencil.sum())
    normal = rng.normal(size=(n, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    b = Reliefboard(42, frame, stencil, rng.uniform(0, 2 * frame.radius, n).astype(np.float32),
                    rng.integers(0, 256, (n, 3), dtype=np.uint8), normal)
    data = encode_board(b)
    assert len(data) <= 84 + (37 * 37 + 7) // 8 + 9 * n
    r = decode_board(data)
    assert r.object_id == 42 and r.frame == frame
    assert np.array_equal(r.stencil, stencil) and np.array_equal(r.color, b.color)
    assert np.abs(r.distance - b.distance).max() <= 2 * frame.radius / 65535
    assert np.degrees(np.arccos(np.clip((r.normal.astype(float) * normal).sum(1), -1, 1))).max() < 0.05
    with pytest.raises(CorruptBlockError, match="object 42"):
        decode_board(data[:-1])
    with pytest.raises(CorruptBlockError, match="header"):
        decode_board(b"nope" + data[4:])
