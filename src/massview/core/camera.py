"""Cameras and viewports: the coordinate contract every rank relies on.

World space is right-handed with +z up. A :class:`Camera` holds float64 position and an
orientation quaternion (w, x, y, z) that rotates camera axes into world axes; the camera looks
down its local -z with +y up (OpenGL convention). Images have a **top-left origin**: pixel
(x, y) is column x, row y counted from the top; a :class:`Viewport` is a pixel rectangle of the
destination image in that frame.

The sub-frustum of a viewport is the off-axis projection whose near-plane window covers
exactly those pixels of the full image, so tiles rendered with it assemble to the full frame.
(On Mesa llvmpipe a tile-sized target with this projection differs from the full-frame render
at ~1e-4 of pixels by rasterization rounding; the bit-exact sort-first path renders into a
full-size target with a scissor and the full-frame matrices instead.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import ConfigError

__all__ = ["Viewport", "Camera", "look_at_quaternion", "quaternion_matrix"]


@dataclass(frozen=True)
class Viewport:
    """A pixel rectangle ``[x, x+w) × [y, y+h)`` of the destination image (top-left origin)."""

    x: int
    y: int
    w: int
    h: int

    def __post_init__(self) -> None:
        for name in ("x", "y", "w", "h"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)):
                raise ConfigError(f"Viewport.{name} must be an integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.w < 0 or self.h < 0:
            raise ConfigError(f"Viewport size must be non-negative, got {self.w}x{self.h}")

    @property
    def area(self) -> int:
        return self.w * self.h

    @property
    def empty(self) -> bool:
        return self.w == 0 or self.h == 0

    def slices(self) -> tuple[slice, slice]:
        """Row and column slices of this viewport in a full (H, W) image array."""
        return slice(self.y, self.y + self.h), slice(self.x, self.x + self.w)

    def intersect(self, other: "Viewport") -> "Viewport":
        x0, y0 = max(self.x, other.x), max(self.y, other.y)
        x1 = min(self.x + self.w, other.x + other.w)
        y1 = min(self.y + self.h, other.y + other.h)
        return Viewport(x0, y0, max(0, x1 - x0), max(0, y1 - y0))

    def to_json(self) -> list[int]:
        return [self.x, self.y, self.w, self.h]

    @classmethod
    def from_json(cls, v) -> "Viewport":
        return cls(*(int(a) for a in v))


def quaternion_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(a) for a in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _matrix_quaternion(m: np.ndarray) -> tuple[float, float, float, float]:
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    n = math.sqrt(sum(a * a for a in q))
    q = tuple(a / n for a in q)
    return q if q[0] >= 0 else tuple(-a for a in q)


def look_at_quaternion(eye, target, up=(0.0, 0.0, 1.0), heading=None) -> tuple[float, float, float, float]:
    """Orientation of a camera at ``eye`` looking at ``target`` with ``up`` as the world up.
    Looking straight along ``up`` (down at the nadir, or up at the zenith) leaves the roll open:
    ``heading``, a direction across ``up``, then says where the top of the image points (the
    limit of views that look slightly towards it: a path passing over its target keeps its roll,
    see :meth:`paths.KeyframePath.pose`); without it (or with one along ``up``) the image's top
    is world +y (its right +x when looking down)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    f = target - eye
    if np.linalg.norm(f) == 0:
        raise ConfigError("look-at target coincides with the camera position")
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    if np.linalg.norm(s) < 1e-9 and heading is not None:  # along up: the limit of views tilted towards heading
        s = np.cross(np.asarray(heading, dtype=np.float64), up)
    if np.linalg.norm(s) < 1e-9:  # looking straight along up: pick any perpendicular
        s = np.cross(f, np.array([0.0, 1.0, 0.0]))
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    return _matrix_quaternion(np.stack([s, u, -f], axis=1))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera, float64 throughout.

    position: world (x, y, z); orientation: unit quaternion (w, x, y, z), camera-to-world;
    fovy: vertical field of view in degrees; near/far: clip distances (world units, > 0);
    width/height: image size in pixels.
    """

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    fovy: float = 45.0
    near: float = 0.1
    far: float = 1000.0
    width: int = 1280
    height: int = 1024
    _rot: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        pos = tuple(float(a) for a in self.position)
        q = np.asarray(self.orientation, dtype=np.float64)
        if len(pos) != 3 or q.shape != (4,) or not np.all(np.isfinite(pos)) or not np.all(np.isfinite(q)):
            raise ConfigError("Camera needs a finite 3-vector position and a (w, x, y, z) quaternion")
        n = np.linalg.norm(q)
        if n == 0:
            raise ConfigError("Camera orientation quaternion is zero")
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "orientation", tuple(float(a) for a in q / n))
        if not 0 < self.fovy < 180:
            raise ConfigError(f"Camera fovy must be in (0, 180) degrees, got {self.fovy}")
        if not 0 < self.near < self.far:
            raise ConfigError(f"Camera needs 0 < near < far, got near={self.near} far={self.far}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ConfigError(f"Camera image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "fovy", float(self.fovy))
        object.__setattr__(self, "near", float(self.near))
        object.__setattr__(self, "far", float(self.far))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "_rot", quaternion_matrix(self.orientation))

    # -- construction -------------------------------------------------------------------
    @classmethod
    def look_at(cls, eye, target, up=(0.0, 0.0, 1.0), **kw) -> "Camera":
        return cls(position=tuple(eye), orientation=look_at_quaternion(eye, target, up), **kw)

    def replace(self, **kw) -> "Camera":
        d = {k: getattr(self, k) for k in ("position", "orientation", "fovy", "near", "far", "width", "height")}
        d.update(kw)
        return Camera(**d)

    def to_json(self) -> dict:
        return {
            "position": list(self.position),
            "orientation": list(self.orientation),
            "fovy": self.fovy,
            "near": self.near,
            "far": self.far,
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_json(cls, d: dict) -> "Camera":
        return cls(**{k: d[k] for k in ("position", "orientation", "fovy", "near", "far", "width", "height")})

    def __reduce__(self):
        return (Camera.from_json, (self.to_json(),))

    # -- geometry -----------------------------------------------------------------------
    @property
    def viewport(self) -> Viewport:
        return Viewport(0, 0, self.width, self.height)

    @property
    def forward(self) -> np.ndarray:
        return -self._rot[:, 2]

    @property
    def right(self) -> np.ndarray:
        return self._rot[:, 0]

    @property
    def up(self) -> np.ndarray:
        return self._rot[:, 1]

    def view_matrix(self) -> np.ndarray:
        """4x4 world-to-camera matrix (float64, column vectors: ``p_cam = V @ p_world``)."""
        v = np.eye(4)
        v[:3, :3] = self._rot.T
        v[:3, 3] = -self._rot.T @ np.asarray(self.position)
        return v

    def window(self, vp: Viewport | None = None) -> tuple[float, float, float, float]:
        """Near-plane window (left, right, bottom, top) covering the pixels of ``vp``."""
        t = self.near * math.tan(math.radians(self.fovy) / 2)
        r = t * self.width / self.height
        if vp is None:
            return -r, r, -t, t
        left = -r + 2 * r * vp.x / self.width
        right = -r + 2 * r * (vp.x + vp.w) / self.width
        top = t - 2 * t * vp.y / self.height
        bottom = t - 2 * t * (vp.y + vp.h) / self.height
        return left, right, bottom, top

    def projection_matrix(self, vp: Viewport | None = None) -> np.ndarray:
        """4x4 OpenGL projection of the full frame, or the off-axis sub-frustum of ``vp``."""
        left, right, bottom, top = self.window(vp)
        n, f = self.near, self.far
        p = np.zeros((4, 4))
        p[0, 0] = 2 * n / (right - left)
        p[1, 1] = 2 * n / (top - bottom)
        p[0, 2] = (right + left) / (right - left)
        p[1, 2] = (top + bottom) / (top - bottom)
        p[2, 2] = -(f + n) / (f - n)
        p[2, 3] = -2 * f * n / (f - n)
        p[3, 2] = -1.0
        return p

    def view_projection(self, vp: Viewport | None = None) -> np.ndarray:
        return self.projection_matrix(vp) @ self.view_matrix()

    def frustum_planes(self, vp: Viewport | None = None) -> np.ndarray:
        """(6, 4) float64 planes (a, b, c, d), normals pointing inward and normalized:
        a point p is inside when ``a*px + b*py + c*pz + d >= 0`` for all six.
        Order: left, right, bottom, top, near, far.
        A ``vp`` without pixels (a sort-first tile of a frame smaller than its tiles) sees
        nothing: the full frame's planes pushed out of reach, so every test rejects all."""
        if vp is not None and (vp.w <= 0 or vp.h <= 0):
            planes = self.frustum_planes()
            planes[:, 3] = -1e300
            return planes
        m = self.view_projection(vp)
        planes = np.array([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]])
        return planes / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) world points to pixel coordinates (N, 2) (top-left origin) and the
        camera-space depth along the view direction (N,); points behind have depth <= 0."""
        p = np.asarray(points, dtype=np.float64)
        h = p @ self.view_projection()[:, :3].T + self.view_projection()[:, 3]
        w = h[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            ndc = h[:, :2] / w[:, None]
        px = np.empty_like(ndc)
        px[:, 0] = (ndc[:, 0] + 1) * 0.5 * self.width
        px[:, 1] = (1 - ndc[:, 1]) * 0.5 * self.height
        return px, w
