"""Synthetic elevation: ridged multifractal value noise, deterministic at any tiling.

Each octave is value noise: pseudo-random lattice values (a 64-bit integer hash of the global
lattice coordinates, the octave and the seed) interpolated with quintic smoothstep weights,
on a lattice rotated by a different angle per octave (no axis-aligned creases). Every sample depends
only on its global (row, col), so any window gives the same values as the whole grid, and
memory grows with the window, not with N.

Relief: a low-frequency fBm base (plains and basins) plus Musgrave's ridged multifractal
(sharp ridges, each octave weighted by the previous one), shaped so valleys flatten.
Heights are in metres (about 0–2500 m) at 30 m spacing.
"""

from __future__ import annotations

import numpy as np

from ...core.errors import ConfigError

__all__ = ["synthetic_heights", "SYNTHETIC_SPACING"]

SYNTHETIC_SPACING = 30.0
_M1, _M2 = np.uint64(0xFF51AFD7ED58CCD5), np.uint64(0xC4CEB9FE1A85EC53)


def _hash01(gy: np.ndarray, gx: np.ndarray, salt: int) -> np.ndarray:
    h = (gx.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) ^ (gy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F))
    h ^= np.uint64(salt & 0xFFFFFFFFFFFFFFFF)
    h ^= h >> np.uint64(33)
    h *= _M1
    h ^= h >> np.uint64(33)
    h *= _M2
    h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def _smooth(f: np.ndarray) -> np.ndarray:
    return f * f * f * (f * (f * 6 - 15) + 10)


def _value_noise(rows: np.ndarray, cols: np.ndarray, period: float, angle: float, salt: int) -> np.ndarray:
    """Value noise on a lattice of spacing ``period`` rotated by ``angle`` (radians)."""
    ca, sa = np.float64(np.cos(angle)), np.float64(np.sin(angle))
    # rotated lattice coordinates, computed in float64 from global indices (tiling-exact)
    u = (cols[None, :] * ca - rows[:, None] * sa) / period
    v = (cols[None, :] * sa + rows[:, None] * ca) / period
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = _smooth((u - iu).astype(np.float32)), _smooth((v - iv).astype(np.float32))
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    u0, v0 = iu.min(), iv.min()
    lat = _hash01(np.arange(v0, iv.max() + 2)[:, None], np.arange(u0, iu.max() + 2)[None, :], salt).astype(np.float32)
    iu -= u0
    iv -= v0
    w = lat.shape[1]
    flat = lat.ravel()
    idx = iv * w + iu
    a, b = flat[idx], flat[idx + 1]
    c, d = flat[idx + w], flat[idx + w + 1]
    top = a + (b - a) * fu
    return top + ((c + (d - c) * fu) - top) * fv


def synthetic_heights(r0: int, r1: int, c0: int, c1: int, size: int, seed: int = 1) -> np.ndarray:
    """Heights (float32, metres) of rows r0:r1, cols c0:c1 of the ``size`` × ``size`` DEM."""
    if size < 2:
        raise ConfigError(f"--size must be at least 2, got {size}")
    rows = np.arange(r0, r1, dtype=np.float64)
    cols = np.arange(c0, c1, dtype=np.float64)
    base_period = max(size / 1.5, 8.0)
    salt = seed * 0x5851F42D4C957F2D
    base = np.zeros((len(rows), len(cols)), np.float32)
    amp, total = 1.0, 0.0
    for o in range(4):  # broad fBm for basins and plateaus
        base += amp * _value_noise(rows, cols, base_period / 2**o, 0.7 + 1.9 * o, salt + 101 * o)
        total += amp
        amp *= 0.5
    base /= total
    ridged = np.zeros_like(base)
    weight = np.ones_like(base)
    period, amp = max(size / 3.0, 8.0), 1.0
    o = 0
    while period >= 2.0 and o < 14:
        v = _value_noise(rows, cols, period, 0.3 + 2.4 * o, salt + 7919 * (o + 1))
        signal = (1.0 - np.abs(2 * v - 1)) ** 2 * weight
        ridged += amp * signal
        weight = np.clip(signal * 2.0, 0, 1)
        period /= 2.0
        amp *= 0.5
        o += 1
    h = 0.55 * base + 0.45 * ridged
    h = np.clip(h - 0.12, 0, None) ** 1.35  # flatten valleys, sharpen peaks
    return (h * 2600.0).astype(np.float32)
