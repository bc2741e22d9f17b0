"""The synthetic DEM as a raster source and as files (``.npy`` / GeoTIFF), written tile by tile."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ...core.errors import ConfigError
from ..generators.terrain import SYNTHETIC_SPACING, synthetic_heights
from .sources import RasterSource

__all__ = ["SyntheticSource", "write_synthetic"]

_TILE = 1024  # rows per strip
_TILE_COLS = 4096  # columns per window: the generator's temporaries are ~120 MiB per 1024 × 4096 window


class SyntheticSource(RasterSource):
    def __init__(self, size: int, seed: int = 1):
        if size < 2:
            raise ConfigError(f"--size must be at least 2, got {size}")
        self.rows = self.cols = int(size)
        self.size, self.seed = int(size), int(seed)
        self.dtype = np.dtype(np.float32)
        self.name = f"synthetic:{size}:seed{seed}"
        self.transform = (0.0, SYNTHETIC_SPACING, 0.0, 0.0, 0.0, -SYNTHETIC_SPACING)

    def _raw(self, r0, r1, c0, c1):
        return synthetic_heights(r0, r1, c0, c1, self.size, self.seed)


def write_synthetic(path: Path, size: int, seed: int, fmt: str, progress: Callable[[int, int], None] | None = None) -> None:
    """Write the DEM as ``.npy`` (memory-mapped) or tiled GeoTIFF, one row of tiles at a time,
    each generated in windows of at most 1024 × 4096 samples (the generator's float64
    temporaries of a full 32769-wide strip would take ~3.7 GiB); the window does not change
    the values."""
    src = SyntheticSource(size, seed)
    prog = progress or (lambda a, t: None)
    strips = range(0, size, _TILE)
    tmp = path.with_name(path.name + ".partial")
    try:
        _write(tmp, src, size, fmt, strips, prog)
    except BaseException:
        tmp.unlink(missing_ok=True)  # (a full disk, Ctrl-C: no half-written file left)
        raise
    tmp.replace(path)


def _write(tmp: Path, src, size: int, fmt: str, strips, prog) -> None:
    if fmt == "npy":
        from .workers import resolve_workers, run_ordered

        out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=(size, size))

        def window(r0: int, r1: int, c0: int) -> int:
            out[r0:r1, c0:c0 + _TILE_COLS] = src.read(r0, r1, c0, min(c0 + _TILE_COLS, size))
            return r1 - r0 if c0 + _TILE_COLS >= size else 0

        windows = ((lambda r0=r0, c0=c0: window(r0, min(r0 + _TILE, size), c0)) for r0 in strips for c0 in range(0, size, _TILE_COLS))
        run_ordered(resolve_workers(None), windows, lambda n: n and (out.flush(), prog(n, size)))  # windows on every core
        out.flush()
        del out
    elif fmt == "tif":
        import rasterio
        from rasterio.transform import Affine
        from rasterio.windows import Window

        profile = dict(driver="GTiff", width=size, height=size, count=1, dtype="float32", tiled=True,
                       blockxsize=256, blockysize=256, compress="deflate", predictor=3, BIGTIFF="IF_SAFER",
                       transform=Affine(SYNTHETIC_SPACING, 0, 0, 0, -SYNTHETIC_SPACING, 0))
        with rasterio.open(tmp, "w", **profile) as ds:
            for r0 in strips:
                r1 = min(r0 + _TILE, size)
                for c0 in range(0, size, _TILE_COLS):
                    c1 = min(c0 + _TILE_COLS, size)
                    ds.write(src.read(r0, r1, c0, c1), 1, window=Window(c0, r0, c1 - c0, r1 - r0))
                prog(r1 - r0, size)
    else:
        raise ConfigError(f"--format {fmt!r}: use store, tif or npy")
