"""Partial and final images as they travel between ranks.

An :class:`Image` is RGBA8 color ``(h, w, 4) uint8`` plus float32 window-space depth
``(h, w)`` in [0, 1] (1.0 = background / far plane), covering a :class:`Viewport` of the
destination image, top-left origin. Background pixels carry depth exactly 1.0 and the
background color.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Viewport
from .errors import ConfigError

__all__ = ["Image", "BACKGROUND_RGBA", "blank_image"]

BACKGROUND_RGBA = (22, 26, 34, 255)


@dataclass
class Image:
    color: np.ndarray  # (h, w, 4) uint8
    depth: np.ndarray  # (h, w) float32
    viewport: Viewport

    def __post_init__(self) -> None:
        h, w = self.viewport.h, self.viewport.w
        if self.color.shape != (h, w, 4) or self.color.dtype != np.uint8:
            raise ConfigError(f"Image color must be ({h}, {w}, 4) uint8, got {self.color.shape} {self.color.dtype}")
        if self.depth.shape != (h, w) or self.depth.dtype != np.float32:
            raise ConfigError(f"Image depth must be ({h}, {w}) float32, got {self.depth.shape} {self.depth.dtype}")

    @property
    def nbytes(self) -> int:
        return self.color.nbytes + self.depth.nbytes

    def crop(self, vp: Viewport) -> "Image":
        """The part of this image inside ``vp`` (destination pixel coordinates)."""
        v = self.viewport.intersect(vp)
        rows = slice(v.y - self.viewport.y, v.y - self.viewport.y + v.h)
        cols = slice(v.x - self.viewport.x, v.x - self.viewport.x + v.w)
        return Image(np.ascontiguousarray(self.color[rows, cols]), np.ascontiguousarray(self.depth[rows, cols]), v)

    def paste(self, other: "Image") -> None:
        """Copy ``other`` (which must lie inside this image's viewport) into place."""
        v = other.viewport
        if v.empty:
            return
        rows = slice(v.y - self.viewport.y, v.y - self.viewport.y + v.h)
        cols = slice(v.x - self.viewport.x, v.x - self.viewport.x + v.w)
        self.color[rows, cols] = other.color
        self.depth[rows, cols] = other.depth


def blank_image(vp: Viewport) -> Image:
    color = np.empty((vp.h, vp.w, 4), np.uint8)
    color[:] = BACKGROUND_RGBA
    return Image(color, np.ones((vp.h, vp.w), np.float32), vp)
