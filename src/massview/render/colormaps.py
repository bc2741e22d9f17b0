"""View-time terrain shading parameters and colour ramps.

:class:`Shading` holds what a user may change while viewing (no re-ingest): vertical
exaggeration, the sun (GDAL's convention: azimuth in degrees clockwise from north, altitude in
degrees above the horizon), the colour ramp and the haze strength. Ramps are 256-entry RGB
tables over the store's height range: ``hypsometric`` (massview's own lowland-green to snow
ramp), any matplotlib colormap name, ``ortho`` (the store's orthophoto) or ``none`` (uniform
grey, shading alone).
"""

from __future__ import annotations

import atexit
import math
import os
import threading
from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError

__all__ = ["Shading", "ramp", "paint_sky", "load_sky_kernel", "SKY_KERNELS", "SPECIAL_COLORMAPS"]

SPECIAL_COLORMAPS = ("hypsometric", "ortho", "none")
DRAPE_COLORMAPS = ("auto", "ortho")  # the colour maps under which a store's orthophoto is drawn
_STOPS = np.array([0.0, 0.18, 0.42, 0.7, 0.88, 1.0])
_RGB = np.array([[64, 112, 70], [110, 150, 82], [186, 172, 120], [140, 122, 104], [170, 165, 160], [245, 245, 250]], np.float32)
SKY_HORIZON = (0.80, 0.86, 0.92)  # sky gradient, also the colour aerial perspective fades to (sky.glsl)
SKY_ZENITH = (0.28, 0.45, 0.72)


@dataclass(frozen=True)
class Shading:
    exaggeration: float = 1.0
    sun: tuple[float, float] = (315.0, 45.0)
    colormap: str = "hypsometric"
    haze: float = 1.0  # 1: 30 % of the way to the sky colour across the terrain's diagonal

    def sun_vector(self) -> tuple[float, float, float]:
        """Unit vector towards the sun in world axes (x east, y north, z up)."""
        az, alt = (math.radians(v) for v in self.sun)
        return (math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt))

    def extinction(self, world_size: float) -> float:
        """Haze per world unit for a terrain whose horizontal diagonal is ``world_size``
        (haze 1: 30 % of the way to the sky colour across the diagonal)."""
        return 0.35 * float(self.haze) / max(float(world_size), 1e-9)


LIGHT_WEIGHTS = (0.30, 0.95)  # terrain lighting: sky (ambient) and sun weights (T1 and T2)


def haze_start(eye, lo, hi, size: float) -> float:
    """How far from ``eye`` haze starts for a terrain in the box ``lo``..``hi`` whose horizontal
    diagonal is ``size``: 0 while the box is within one diagonal of the eye (every default
    path), else the distance beyond that. Haze is "30 % across the diagonal": measured from the
    eye alone, an eye standing far back (the orbit fitted to a tall narrow frame stands ~50
    diagonals away) saw the whole terrain fade into the sky."""
    d = math.sqrt(sum(max(l - e, 0.0, e - h) ** 2 for e, l, h in zip((float(v) for v in eye), lo, hi)))
    return max(d - size, 0.0)


def ramp(name: str) -> np.ndarray:
    """(256, 3) uint8 colour table for ``name`` (grey for ``ortho``/``none``)."""
    t = np.linspace(0.0, 1.0, 256)
    if name in ("ortho", "none"):
        return np.full((256, 3), 209, np.uint8)
    if name == "hypsometric":
        return np.stack([np.interp(t, _STOPS, _RGB[:, c]) for c in range(3)], axis=-1).astype(np.uint8)
    import matplotlib

    try:
        cmap = matplotlib.colormaps[name]
    except KeyError:
        raise ConfigError(f"--colormap {name!r} is not a matplotlib colormap; use one of {', '.join(SPECIAL_COLORMAPS)} "
                          "or a matplotlib name such as terrain, gist_earth, viridis, cividis") from None
    return (np.asarray(cmap(t))[:, :3] * 255 + 0.5).astype(np.uint8)


SKY_KERNELS = ("auto", "numpy", "numba")
SKY_KERNEL_ENV = "MASSVIEW_SKY_KERNEL"
_LOADER: dict = {"thread": None, "fn": None, "error": None}
_LOADER_LOCK = threading.Lock()


def load_sky_kernel(wait: bool = False):
    """The compiled sky kernel (:func:`massview.data.skykernel.paint`) once it is loaded,
    else None. The first call starts loading it (importing numba, loading or compiling the
    cached kernel: about a second) on a thread, so no frame waits for it: until it is ready
    :func:`paint_sky` paints with numpy, which gives the same bytes. ``wait`` blocks until the
    load ends. A process that exits while it loads waits for it first (numba must not be torn
    down mid-compile). Where numba cannot load, None for good (numpy paints)."""
    with _LOADER_LOCK:
        if _LOADER["thread"] is None:
            thread = threading.Thread(target=_load, name="massview-sky-kernel", daemon=True)
            _LOADER["thread"] = thread
            thread.start()
            atexit.register(thread.join)
    if wait:
        _LOADER["thread"].join()
    return _LOADER["fn"]


def _load() -> None:
    try:
        from ..data.skykernel import paint

        z = np.zeros(1)
        paint(np.zeros((1, 1, 4), np.uint8), np.ones((1, 1), np.float32), z, z, z, z, 0.0, np.zeros(3), np.zeros(3))
        _LOADER["fn"] = paint
    except Exception as exc:  # noqa: BLE001 - numba missing or broken: the numpy path stays
        _LOADER["error"] = exc


def _kernel_choice(kernel: str | None) -> str:
    choice = kernel or os.environ.get(SKY_KERNEL_ENV) or "auto"
    if choice not in SKY_KERNELS:
        where = "kernel" if kernel else SKY_KERNEL_ENV
        raise ConfigError(f"{where}={choice!r} is not a sky kernel; use one of {', '.join(SKY_KERNELS)}")
    return choice


def paint_sky(camera, img, kernel: str | None = None):
    """``img`` (an Image of the final frame or a tile of it) with its background pixels (depth
    1) painted with the sky gradient along each pixel's view ray — done once on the assembled
    pixels, so compositing and image codecs keep treating the background as empty.

    ``kernel`` (default ``MASSVIEW_SKY_KERNEL``, else ``auto``): ``numba`` paints with the
    compiled one-pass kernel (:mod:`massview.data.skykernel`, loaded first if need be), ``numpy`` with the
    numpy code below, ``auto`` with the compiled kernel once :func:`load_sky_kernel` has it and
    with numpy until then. All three give the same bytes.

    The ray terms are separable (one vector per row, one per column), so they are evaluated
    only at the background pixels: the same float64 operations in the same order as a
    whole-image evaluation, hence the same bytes, at a cost proportional to the sky's area.
    Rows that are all sky (most of it in a terrain view) are evaluated densely by broadcasting
    the row and column terms, in blocks of about ``_BLOCK`` pixels that stay in cache, and
    written as whole rows; only rows the horizon crosses gather their background pixels."""
    choice = _kernel_choice(kernel)
    fn = load_sky_kernel(wait=choice == "numba") if choice != "numpy" else None
    if choice == "numba" and fn is None:
        raise ConfigError(f"sky kernel 'numba' could not be loaded ({_LOADER['error']}); use {SKY_KERNEL_ENV}=numpy")
    if fn is not None:
        color = img.color.copy()
        terms = _terms(camera, img.viewport)
        if not fn(color, img.depth, *terms[:4], float(terms[4]), np.array(SKY_HORIZON), np.array(SKY_ZENITH)):
            return img
        return type(img)(color, img.depth, img.viewport)
    bg = img.depth >= 1.0
    count = np.count_nonzero(bg, axis=1)
    if not count.any():
        return img
    vp = img.viewport
    terms = _terms(camera, vp)
    color = img.color.copy()
    step = max(1, _BLOCK // vp.w)
    full = np.flatnonzero(count == vp.w)
    for a in range(0, full.size, step):  # whole rows of sky, a block of rows at a time
        rows = full[a:a + step]
        dz = _elevation(terms, rows[:, None], slice(None))
        color[rows] = _sky_rgba(dz.ravel()).reshape(len(rows), vp.w, 4)
    partial = (count > 0) & (count < vp.w)
    if partial.any():
        rows, cols = np.nonzero(bg & partial[:, None])
        color[rows, cols] = _sky_rgba(_elevation(terms, rows, cols))
    return type(img)(color, img.depth, vp)


_BLOCK = 1 << 16  # pixels per block of whole sky rows (float64 temporaries of 512 KiB)


def _terms(camera, vp):
    """The separable terms of the view rays' elevation over ``vp``: (row term, column term,
    row², column², r22) as :func:`_elevation` takes them."""
    t = math.tan(math.radians(camera.fovy) / 2)
    px = (vp.x + np.arange(vp.w) + 0.5) / camera.width * 2 - 1
    py = 1 - (vp.y + np.arange(vp.h) + 0.5) / camera.height * 2
    rot = np.asarray(camera.view_matrix())[:3, :3].T  # camera-to-world
    col_x = px * t * camera.width / camera.height
    return (py * t * rot[2, 1], col_x * rot[2, 0], (py * t) ** 2, col_x ** 2, rot[2, 2])


def _elevation(terms, rows, cols) -> np.ndarray:
    """Sines of the view rays' elevation (float64) at ``rows`` × ``cols`` (index arrays that
    broadcast): (row term + column term − r22) / √(column² + row² + 1), in this order."""
    a_row, a_col, n_row, n_col, r22 = terms
    dz = a_row[rows] + a_col[cols]
    dz -= r22
    norm = n_col[cols] + n_row[rows]
    norm += 1.0
    np.sqrt(norm, out=norm)
    dz /= norm
    return dz


def _sky_rgba(e: np.ndarray) -> np.ndarray:
    """(n, 4) uint8 sky colours for the sines of elevation ``e`` (float64, consumed in place):
    smoothstep(-0.05, 0.6, e) between horizon and zenith, as sky.glsl."""
    e += 0.05
    e /= 0.65
    np.clip(e, 0, 1, out=e)
    s = e * e * (3 - 2 * e)
    hor, zen = np.array(SKY_HORIZON), np.array(SKY_ZENITH)
    out = np.empty((e.size, 4), np.uint8)
    out[:, 3] = 255
    for ch in range(3):
        v = s * (zen[ch] - hor[ch])
        v += hor[ch]
        v *= 255
        v += 0.5
        out[:, ch] = v
    return out
