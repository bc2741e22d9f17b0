"""Checks of a DEM input that prepares but would render wrong or cost far too much: a shape
whose padded square is mostly padding (refused before anything is written), an untagged void
marker or fill value among the heights, and a transform in degrees without a CRS (warnings
naming the option that fixes them)."""

from __future__ import annotations

import numpy as np

from ...core.errors import IngestError
from .layout import TerrainLayout
from .sources import RasterSource

__all__ = ["check_padding", "marker_hints", "looks_like_degrees"]

_MAX_PADDING = 64  # the padded square may hold at most this many times the input's samples ...
_SMALL_SQUARE = 4097  # ... unless its side is no more than this (a small input: whatever its shape, it is cheap)


def check_padding(src: RasterSource, lay: TerrainLayout) -> None:
    """Refuse, before anything is written, an input so thin that its padded square would be
    mostly padding (walk9 H2: a 3 × 100000 strip of 1.2 MB grew towards a 131073² store, many
    GB on disk and in memory, and rendered as a line too thin to see)."""
    pad, have = lay.S * lay.S, src.rows * src.cols
    if lay.S > _SMALL_SQUARE and pad > _MAX_PADDING * have:
        raise IngestError(f"{src.name}: {src.rows} x {src.cols} samples would be padded to a square of {lay.S}² "
                          f"({pad / 1e6:,.0f} M samples, {pad / have:,.0f}x the input; about {pad * 9.0 / 1e9:,.1f} GB on disk): "
                          "the terrain layout is square, so a strip this thin costs what a square DEM of its length does and "
                          f"is mostly padding. Crop it, or cut it into pieces closer to square (at most {_MAX_PADDING}x padding, "
                          "e.g. gdal_translate -srcwin) and prepare each")


_MARKERS = (-9999.0, -99999.0, -32767.0, -32768.0)  # usual nodata values of rasters written without a tag
_NOT_A_HEIGHT = 1e15  # |z| beyond this is a fill value (float32's ±3.4e38, 1e30), not a height in any unit


def marker_hints(src: RasterSource, zlo: float, zhi: float) -> list[str]:
    """Warnings for an input without a nodata value whose lowest or highest height is a usual
    void marker: int16's smallest (SRTM's −32768), a float raster's −9999 and the like, or a
    fill value no height can be (±3.4e38): with it the height range, the colours and the
    default camera all follow the marker (a blank render)."""
    if src.nodata is not None:
        return []
    out, dt = [], np.dtype(src.dtype)
    int_min = dt.kind == "i" and zlo == float(np.iinfo(dt).min)
    if int_min:
        lo = int(np.iinfo(dt).min)
        out.append(f"{src.name}: its lowest height is {lo}, the smallest {dt.name} and the usual void marker (SRTM's); "
                   f"if those samples are voids, prepare again with --nodata {lo} --overwrite (they are heights of {lo} now)")
    for z, which in ((zlo, "lowest"), (zhi, "highest")):
        if abs(z) >= _NOT_A_HEIGHT:
            out.append(f"{src.name}: its {which} height is {z:.9g}, a fill value rather than a height; the height range, the "
                       f"colours and the camera follow it, so renders show only sky: if those samples are voids, prepare "
                       f"again with --nodata {z:.9g} --overwrite")
    if zlo in _MARKERS and not int_min:  # (the smallest integer has its own line above)
        out.append(f"{src.name}: its lowest height is {zlo:g}, a usual nodata value; if those samples are voids, prepare "
                   f"again with --nodata {zlo:g} --overwrite (they are heights of {zlo:g} now)")
    return out


def looks_like_degrees(src: RasterSource, relief: float) -> bool:
    """A transform whose samples are under 0.01 units apart, whose extent lies within ±180 × ±90
    and whose heights span more than 5 times that extent: longitude and latitude under heights
    in metres, almost surely (a close-range scan in metres has spacing, extent and relief alike:
    walk10 M1)."""
    x0, dx, _, y0, _, dy = src.transform
    x1, y1 = x0 + dx * src.cols, y0 + dy * src.rows
    extent = max(abs(x1 - x0), abs(y1 - y0))
    return (0 < max(abs(dx), abs(dy)) < 0.01 and max(abs(x0), abs(x1)) <= 180 and max(abs(y0), abs(y1)) <= 90
            and relief > 5 * extent)
