"""Framing a box: clip planes fitted to it (:func:`scene_clip`), and where a camera looking
at it from a given direction stands so that the whole box is in view, centred.

Shared by the ``orbit`` path, the ``walkthrough`` and ``flyover`` paths round a scene with no
ground to walk on (:mod:`massview.core.paths`) and the web viewer's first view of a polygon
scene (:func:`overview_camera`). World units, +z up; directions point from the box's middle
towards the eye.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Camera, look_at_quaternion

__all__ = ["OVERVIEW_AZIMUTH", "OVERVIEW_ELEVATION", "direction", "framed_eye", "framed_camera", "overview_camera", "scene_clip"]

OVERVIEW_AZIMUTH = -115.0  # degrees from +x towards +y: the viewer's first look at a scene comes from the
OVERVIEW_ELEVATION = 30.0  # front (-y; a glTF's +z), a little from the left, 30 degrees above the horizon


def scene_clip(lo, hi, positions=None) -> tuple[float, float]:
    """Clip planes (near, far) in world units fitted to the box ``lo``..``hi``: near = 2e-4 of
    the box diagonal, far = 4 diagonals — reaching further when ``positions`` (n, 3) lie far
    outside the box, so the whole box stays inside the far plane from every position."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    diag = float(max(np.linalg.norm(hi - lo), 1e-9))
    far = diag * 4.0
    if positions is not None and len(positions):
        c = (lo + hi) / 2
        reach = float(np.max(np.linalg.norm(np.asarray(positions, np.float64) - c, axis=1))) + diag / 2
        far = max(far, reach * 1.5)
    return diag * 2e-4, far


def direction(azimuth: float, elevation: float) -> np.ndarray:
    """The unit vector (3,) at ``azimuth`` degrees from +x towards +y, ``elevation`` degrees
    above the xy plane."""
    a, e = math.radians(azimuth), math.radians(elevation)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def framed_eye(lo, hi, towards, width: int, height: int, fovy: float, margin: float = 0.05,
               centred: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """(eye (3,), target (3,), nearest): a camera looking along ``-towards`` (unit (3,), not
    vertical; from the box ``lo``..``hi``'s middle towards the eye) that has all 8 corners in
    view with a ``margin`` (fraction of the half-image) for a ``width`` x ``height`` image of
    vertical field of view ``fovy`` degrees; ``nearest``: the box's least view depth from
    there (at a corner: the box is convex).

    Not ``centred``: the eye stands on the ray through the middle and looks at it (``orbit``);
    the picture of the box is then off centre where its near side projects larger than its far
    side (a flat scene seen from 30 degrees sat in the lower part of the frame). ``centred``:
    the eye is shifted across the view (looking along ``-towards`` still) so that the picture
    of the ellipsoid inscribed in the box is centred, and stands as close as all 8 corners
    allow. (Centring the box's own picture put a sphere in its box, or objects under empty
    upper corners, in the frame's upper part.)"""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = (lo + hi) / 2
    v = np.asarray(towards, np.float64) / np.linalg.norm(towards)
    right = np.cross(-v, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, -v)
    ty = math.tan(math.radians(fovy) / 2)
    tx = ty * width / max(height, 1)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) - c
    k = 1.0 + margin
    w, p, q = corners @ v, corners @ right, corners @ up
    d = max(float(np.max(w + k * np.maximum(np.abs(p) / tx, np.abs(q) / ty))), 1e-9)
    if not centred:
        return c + v * d, c, float(np.min(d - w))
    # The ellipsoid c + diag(half) x, |x| <= 1, seen from c + v d + right a + up b along -v: its picture's
    # edges are the roots T of |diag(half)(right + T v)| = a + T d, which sum to 0 at a = right.half²v / d
    # (and b = up.half²v / d). The corners then fit where |p - a| <= (d - w) tx / k (and so for q, b):
    # bisection on d, from where they fit.
    half2 = ((hi - lo) / 2) ** 2
    alpha, beta = float(right @ (half2 * v)), float(up @ (half2 * v))

    def fits(dd: float) -> bool:
        z = dd - w
        return bool(np.all(z > 0) and np.all(np.abs(p - alpha / dd) * k <= tx * z) and np.all(np.abs(q - beta / dd) * k <= ty * z))

    d0, d1 = float(np.max(w)), d
    while not fits(d1):
        d1 *= 2
    for _ in range(60):
        d0, d1 = (d0, (d0 + d1) / 2) if fits((d0 + d1) / 2) else ((d0 + d1) / 2, d1)
    eye = c + v * d1 + right * (alpha / d1) + up * (beta / d1)
    return eye, eye - v, float(np.min(d1 - w))


def framed_camera(lo, hi, towards, width: int, height: int, fovy: float = 45.0, tight_near: bool = True,
                  centred: bool = True) -> Camera:
    """A camera at :func:`framed_eye` (``centred``: the box's picture centred; else looking at
    its middle, as ``orbit``). Clip planes: the scene's (:func:`scene_clip`,
    reaching the eye); with ``tight_near`` the near plane moves out to just before the box (0.9
    of its least depth: depth stays precise), else it stays where a camera that then moves
    into the scene (the viewer's) still needs it."""
    eye, target, nearest = framed_eye(lo, hi, towards, width, height, fovy, centred=centred)
    near, far = scene_clip(lo, hi, eye[None])
    if tight_near:
        near = max(near, 0.9 * nearest)
    return Camera(tuple(eye), look_at_quaternion(eye, target), fovy=fovy, near=near, far=far, width=width, height=height)


def overview_camera(lo, hi, width: int, height: int, fovy: float = 45.0) -> Camera:
    """The whole box ``lo``..``hi`` in view and centred, seen from the front-left and above
    (:data:`OVERVIEW_AZIMUTH`, :data:`OVERVIEW_ELEVATION`): the web viewer's first camera for
    a polygon scene. Its clip planes are the scene's, so the viewer can fly in."""
    return framed_camera(lo, hi, direction(OVERVIEW_AZIMUTH, OVERVIEW_ELEVATION), width, height, fovy, tight_near=False)
