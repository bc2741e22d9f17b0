"""paint_sky evaluates the sky only at background pixels; it must give the same bytes as the
whole-image evaluation it replaced (kept here as the reference), with the numpy code and with
the compiled kernel (data/skykernel.py) alike."""
import math

import numpy as np
import pytest

from massview.core.camera import Camera
from massview.core.image import Image, Viewport
from massview.render.colormaps import SKY_HORIZON, SKY_ZENITH, paint_sky


def _reference(camera, img):
    bg = img.depth >= 1.0
    vp = img.viewport
    t = math.tan(math.radians(camera.fovy) / 2)
    px = (vp.x + np.arange(vp.w) + 0.5) / camera.width * 2 - 1
    py = 1 - (vp.y + np.arange(vp.h) + 0.5) / camera.height * 2
    rot = np.asarray(camera.view_matrix())[:3, :3].T
    dz = (py[:, None] * t * rot[2, 1] + px[None, :] * t * camera.width / camera.height * rot[2, 0] - rot[2, 2])
    norm = np.sqrt((px[None, :] * t * camera.width / camera.height) ** 2 + (py[:, None] * t) ** 2 + 1.0)
    e = dz / norm
    hor, zen = np.array(SKY_HORIZON), np.array(SKY_ZENITH)
    t = np.clip((e + 0.05) / 0.65, 0, 1)
    up = hor + (zen - hor) * (t * t * (3 - 2 * t))[..., None]
    rgb = (up * 255 + 0.5).astype(np.uint8)
    color = img.color.copy()
    color[bg, :3] = rgb[bg]
    color[bg, 3] = 255
    return color


KERNELS = ("numpy", "numba")


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("seed", range(6))
def test_sky_matches_whole_image_reference(seed, kernel):
    rng = np.random.default_rng(seed)
    W, H = 320, 240
    cam = Camera(position=(0, 0, 100), orientation=tuple(rng.normal(size=4)), fovy=float(rng.uniform(20, 80)),
                 width=W, height=H)
    vp = Viewport(0, 0, W, H) if seed % 2 == 0 else Viewport(40, 60, 200, 120)
    depth = np.where(rng.random((vp.h, vp.w)) < 0.5, 1.0, 0.4).astype(np.float32)
    color = rng.integers(0, 256, (vp.h, vp.w, 4), dtype=np.uint8)
    img = Image(color, depth, vp)
    out = paint_sky(cam, img, kernel=kernel)
    assert np.array_equal(out.color, _reference(cam, img))
    assert np.array_equal(out.color[depth < 1], color[depth < 1])  # geometry untouched
    assert np.array_equal(img.color, color)  # the input is not painted


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("seed", range(4))
def test_sky_with_whole_sky_rows_matches_reference(seed, kernel, monkeypatch):
    """A terrain view's mask: whole rows of sky above a wavy horizon, gaps below it (the dense
    whole-row path, in blocks of rows, and the gathered partial rows together)."""
    from massview.render import colormaps as cm

    monkeypatch.setattr(cm, "_BLOCK", 320 * 7)  # several blocks of rows, the last one short
    rng = np.random.default_rng(seed)
    W, H = 320, 240
    cam = Camera(position=(0, 0, 100), orientation=tuple(rng.normal(size=4)), fovy=float(rng.uniform(20, 80)),
                 width=W, height=H)
    vp = Viewport(0, 0, W, H) if seed % 2 == 0 else Viewport(40, 60, 200, 120)
    edge = vp.h * (0.4 + 0.1 * np.sin(np.arange(vp.w) / rng.uniform(5, 40)))
    depth = np.where(np.arange(vp.h)[:, None] < edge[None, :], 1.0, 0.4).astype(np.float32)
    depth[vp.h // 2:, : vp.w // 5] = 1.0
    depth[vp.h - 3:] = 1.0  # whole sky rows at the bottom too
    color = rng.integers(0, 256, (vp.h, vp.w, 4), dtype=np.uint8)
    img = Image(color, depth, vp)
    out = paint_sky(cam, img, kernel=kernel)
    assert (np.count_nonzero(depth >= 1, axis=1) == vp.w).sum() > 10
    assert np.array_equal(out.color, _reference(cam, img))


@pytest.mark.parametrize("kernel", KERNELS)
def test_no_background_returns_the_image(kernel):
    vp = Viewport(0, 0, 8, 8)
    img = Image(np.zeros((8, 8, 4), np.uint8), np.zeros((8, 8), np.float32), vp)
    assert paint_sky(Camera(position=(0, 0, 1), orientation=(0, 0, 0, 1), width=8, height=8), img, kernel=kernel) is img


def test_auto_paints_the_same_while_and_after_the_kernel_loads():
    """``auto`` paints with numpy until the compiled kernel is loaded, then with it: the same
    bytes before and after."""
    from massview.render import colormaps as cm

    rng = np.random.default_rng(7)
    cam = Camera(position=(0, 0, 100), orientation=tuple(rng.normal(size=4)), fovy=50.0, width=160, height=120)
    vp = Viewport(0, 0, 160, 120)
    depth = np.where(rng.random((120, 160)) < 0.4, 1.0, 0.3).astype(np.float32)
    img = Image(rng.integers(0, 256, (120, 160, 4), dtype=np.uint8), depth, vp)
    first = paint_sky(cam, img, kernel="auto")
    assert cm.load_sky_kernel(wait=True) is not None
    assert np.array_equal(paint_sky(cam, img, kernel="auto").color, first.color)
    assert np.array_equal(first.color, _reference(cam, img))


def test_bad_kernel_names_the_setting(monkeypatch):
    from massview.core.errors import ConfigError

    img = Image(np.zeros((4, 4, 4), np.uint8), np.ones((4, 4), np.float32), Viewport(0, 0, 4, 4))
    cam = Camera(position=(0, 0, 1), orientation=(0, 0, 0, 1), width=4, height=4)
    with pytest.raises(ConfigError, match="kernel='gpu'"):
        paint_sky(cam, img, kernel="gpu")
    monkeypatch.setenv("MASSVIEW_SKY_KERNEL", "fast")
    with pytest.raises(ConfigError, match="MASSVIEW_SKY_KERNEL='fast'"):
        paint_sky(cam, img)


@pytest.mark.parametrize("pitch", [-80.0, -30.0, 0.0, 30.0, 80.0])
def test_not_sky_counts_no_sky_pixel_and_every_terrain_colour(pitch):
    """The tests' ``not_sky`` (conftest), which tells the terrain from the painted sky in a PNG:
    a frame that is all sky counts 0 whatever the view, and every colour of the hypsometric
    ramp (shaded darker or lighter) counts."""
    from conftest import not_sky
    from massview.core.image import blank_image
    from massview.render.colormaps import _RGB

    cam = Camera.look_at((0.0, 0.0, 0.0), (1.0, 0.3, math.tan(math.radians(pitch))), width=320, height=240, fovy=60.0)
    sky = paint_sky(cam, blank_image(cam.viewport), kernel="numpy")
    assert not_sky(sky.color[..., :3]) == 0
    ramp = np.clip(_RGB[:, None, :] * np.linspace(0.3, 1.3, 11)[None, :, None], 0, 255).astype(np.uint8)
    assert not_sky(ramp) == ramp.shape[0] * ramp.shape[1]
