"""The walkthrough ``massview bench dmmr`` flies over replicated scenes, and the paper's tables.

:func:`serpentine_path` writes a keyframe path (the format of :mod:`massview.core.paths`)
that sweeps the grid of copies row by row (alternating direction, turning between rows) at
twice the scene height (at least 0.3 of a copy's width), looking ahead and 40° down at the row: every copy passes under the camera, and
the steep view keeps the frustum to the copies near it (as the paper's walkthrough of
§4, "a fixed path walkthrough ... to make all instances of the power plant visible").
:func:`copy_of_objects` maps object centres to copy indices (the generator's grid), so the
bench can check that every copy was drawn. ``PAPER`` holds Tables 1–3 of Revanth &
Narayanan 2012 (ms) for printing beside ours.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["PAPER", "serpentine_path", "copy_of_objects"]

# Revanth & Narayanan 2012, §4, Tables 1-3: frame time and module times in ms (per client: lists)
PAPER = {
    "plants_2": {4: {"frame": 136, "divide": 15.89, "send": 36.83, "assemble": 136.1, "enable_queries": [8.87, 9.99],
                     "retrieve": [1.77, 1.61], "load": [0.44, 0.29], "to_server": [16.48, 11.96]},
                 6: {"frame": 147, "divide": 11.71, "send": 35.29, "assemble": 147.1, "enable_queries": [8.32, 10.27],
                     "retrieve": [1.68, 1.74], "load": [0.37, 0.36], "to_server": [14.14, 15.09]},
                 8: {"frame": 150, "divide": 11.44, "send": 35.64, "assemble": 150.4, "enable_queries": [7.96, 9.70],
                     "retrieve": [1.64, 1.70], "load": [0.34, 0.32], "to_server": [16.12, 12.75]}},
    "plants_4": {4: {"frame": 78, "divide": 18.89, "send": 67.87, "assemble": 78.4, "enable_queries": [4.7, 33.8, 4.9, 29.6],
                     "retrieve": [1.3, 2, 1.3, 2.1], "load": [3.1, 4.4, 0.8, 0.7], "to_server": [18.1, 4.4, 15.2, 3.6]},
                 6: {"frame": 86, "divide": 20.08, "send": 79.1, "assemble": 85.8, "enable_queries": [6.4, 48.1, 10.8, 45.3],
                     "retrieve": [1.4, 2.1, 1.4, 2], "load": [4.6, 4.7, 14.2, 10.9], "to_server": [17, 4.8, 17.6, 6.5]},
                 8: {"frame": 101, "divide": 21.05, "send": 90.41, "assemble": 101.8, "enable_queries": [97.8, 60.7, 80.7, 69.2],
                     "retrieve": [1.7, 2.8, 2, 2.7], "load": [30.2, 8.3, 28.8, 12], "to_server": [29.2, 9.8, 25.6, 30.1]}},
    "cities_4": {16: {"frame": 64, "divide": 9.07, "send": 45.89, "assemble": 64.6, "enable_queries": [1.7, 4.1, 7.5, 3.7],
                      "retrieve": [0.2, 0.4, 0.2, 0.4], "load": [1.5, 0.7, 10.7, 0.5], "to_server": [35.4, 9.1, 37.4, 11.4]},
                 25: {"frame": 79, "divide": 16.18, "send": 44.52, "assemble": 79.3, "enable_queries": [7, 8.2, 4.8, 9.1],
                      "retrieve": [0.4, 0.8, 0.4, 0.7], "load": [11.4, 0.8, 5.1, 0.5], "to_server": [34.6, 11.3, 32.7, 10.4]},
                 36: {"frame": 93, "divide": 16.48, "send": 52.28, "assemble": 93.4, "enable_queries": [3.7, 12.8, 10.1, 13.5],
                      "retrieve": [0.5, 1, 0.6, 0.9], "load": [6.6, 0.9, 11.8, 0.6], "to_server": [35.4, 8.3, 37.5, 14]}},
}


def _grid(copies: int) -> tuple[int, int]:
    side = math.ceil(math.sqrt(copies))  # as data.generators.scenes.copy_offsets
    return side, math.ceil(copies / side)


def serpentine_path(out: Path, lo, hi, copies: int, extent) -> Path:
    """Write the row-by-row sweep over ``copies`` copies of footprint ``extent`` (x, y), placed
    on the generator's grid inside the scene box ``lo``..``hi``; returns the file."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    side, rows = _grid(copies)
    ex, ey = float(extent[0]), float(extent[1])
    h = max(float(hi[2] - lo[2]), 1e-3)
    alt = max(2.0 * h, 0.3 * max(ex, ey))  # twice the height, or higher over flat wide copies
    z = lo[2] + alt
    reach = alt / math.tan(math.radians(40))  # look 40° down
    gx0, gx1 = lo[0], lo[0] + (side - 1) * ex * 1.05 + ex  # the grid's x extent
    keys = []
    for r in range(rows):
        y = lo[1] + r * ey * 1.05 + 0.5 * ey
        d = 1.0 if r % 2 == 0 else -1.0
        looks = np.linspace(gx0, gx1, 2 * side + 1)[:: int(d)]  # the looked-at point sweeps the row
        keys += [([x - d * reach, y, z], [x, y, lo[2]]) for x in looks]
        if r + 1 < rows:  # turn above the row's end, looking back into the grid
            xe, ym = looks[-1], y + 0.525 * ey
            keys.append(([xe, ym, z], [xe - d * 0.5 * ex, ym + 0.2 * ey, lo[2]]))
    pos = np.array([k[0] for k in keys])
    t = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])  # uniform speed
    data = {"keyframes": [{"time": float(ti), "position": p, "look_at": a} for ti, (p, a) in zip(t, keys)]}
    out.write_text(json.dumps(data, indent=1))
    return out


def copy_of_objects(centers: np.ndarray, lo, copies: int, extent) -> np.ndarray:
    """(n,) int copy index of each object centre ((n, 3)) on the generator's grid."""
    side, rows = _grid(copies)
    c = np.asarray(centers, float) - np.asarray(lo, float)[None]
    i = np.clip(np.floor(c[:, 0] / (float(extent[0]) * 1.05)), 0, side - 1).astype(np.int64)
    j = np.clip(np.floor(c[:, 1] / (float(extent[1]) * 1.05)), 0, rows - 1).astype(np.int64)
    return np.minimum(j * side + i, copies - 1)
