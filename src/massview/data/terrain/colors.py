"""Computed terrain colour: hypsometric tint modulated by hillshade (used when no orthophoto
is given). Works on one block at a time; heights in metres, spacing in metres per sample."""

from __future__ import annotations

import numpy as np

__all__ = ["shade_block"]

# elevation fraction → RGB (lowland green, upland ochre, rock grey, snow)
_STOPS = np.array([0.0, 0.18, 0.42, 0.7, 0.88, 1.0])
_RGB = np.array([[64, 112, 70], [110, 150, 82], [186, 172, 120], [140, 122, 104], [170, 165, 160], [245, 245, 250]], np.float32)


def shade_block(h: np.ndarray, dx: float, dy: float, zlo: float, zhi: float, vscale: float = 1.0) -> np.ndarray:
    """(M, M, 3) uint8 colour of a block of heights ``h`` (rows = +y southward)."""
    t = np.clip((h - zlo) / max(zhi - zlo, 1e-6), 0, 1)
    rgb = np.stack([np.interp(t, _STOPS, _RGB[:, c]) for c in range(3)], axis=-1)
    gy, gx = np.gradient(h.astype(np.float32) * vscale, dy, dx)
    # light from the north-west, 45° up; rows grow southward so north is -row
    nx, ny, nz = -gx, gy, np.ones_like(gx)
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    lx, ly, lz = -0.5, 0.5, 0.7071
    shade = np.clip((nx * lx + ny * ly + nz * lz) / norm, 0, 1)
    return np.clip(rgb * (0.45 + 0.75 * shade[..., None]), 0, 255).astype(np.uint8)
