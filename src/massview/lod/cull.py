"""View-frustum culling and screen footprints of bounded items (objects, patches, blocks).

Plain numpy over arrays of bounding spheres and boxes; planes come from
:meth:`Camera.frustum_planes` (inward normals, normalized).
"""

from __future__ import annotations

import numpy as np

from ..core.camera import Camera

__all__ = ["spheres_in_frustum", "boxes_in_frustum", "screen_rects", "frustum_planes"]


_PLANES: list = []  # the last few (camera, viewport, planes): a frame's stages ask for the same ones


def frustum_planes(camera: Camera, vp=None) -> np.ndarray:
    """:meth:`Camera.frustum_planes` (read-only), remembered for the last few (camera, viewport)
    pairs: a frame's LOD stage asks for the same camera's planes several times. Cameras are
    immutable and the cache holds them, so an entry is found by identity."""
    for cam, v, planes in _PLANES:
        if cam is camera and v == vp:
            return planes
    planes = camera.frustum_planes(vp)
    planes.flags.writeable = False
    _PLANES.insert(0, (camera, vp, planes))
    del _PLANES[4:]
    return planes


def spheres_in_frustum(centers: np.ndarray, radii: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(n,) bool: the sphere is not entirely outside any plane (conservative)."""
    d = centers @ planes[:, :3].T + planes[:, 3]
    return np.all(d >= -radii[:, None], axis=1)


def boxes_in_frustum(lo: np.ndarray, hi: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(n,) bool: the axis-aligned box is not entirely outside any plane (conservative)."""
    n = planes[:, :3]
    # the box corner farthest along each plane normal (the "p-vertex")
    p = np.where(n[None, :, :] >= 0, hi[:, None, :], lo[:, None, :])
    d = np.einsum("bpk,pk->bp", p, n) + planes[:, 3]
    return np.all(d >= 0, axis=1)


def screen_rects(camera: Camera, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(n, 4) float64 pixel rectangles [x0, y0, x1, y1] (top-left origin, clipped to the image)
    bounding the projection of each box. A box reaching behind the near plane covers the
    whole image (conservative)."""
    n = len(lo)
    if n == 0:
        return np.zeros((0, 4))
    corners = np.stack([np.where(np.array([(i >> k) & 1 for k in range(3)], bool), hi, lo) for i in range(8)], axis=1)
    px, w = camera.project(corners.reshape(-1, 3))
    px = px.reshape(n, 8, 2)
    w = w.reshape(n, 8)
    behind = np.any(w <= camera.near * 0.999, axis=1)
    with np.errstate(invalid="ignore"):
        rect = np.concatenate([px.min(axis=1), px.max(axis=1)], axis=1)
    rect[behind] = [0, 0, camera.width, camera.height]
    rect[:, [0, 2]] = np.clip(rect[:, [0, 2]], 0, camera.width)
    rect[:, [1, 3]] = np.clip(rect[:, [1, 3]], 0, camera.height)
    return rect
