"""Camera paths: JSON keyframes with smooth interpolation, and built-in parametric paths.

A path maps a parameter t ∈ [0, 1] to a :class:`Camera`. Keyframe files are JSON::

    {"keyframes": [
        {"time": 0.0, "position": [x, y, z], "look_at": [x, y, z]},
        {"time": 2.5, "position": [x, y, z], "orientation": [w, x, y, z]}
     ],
     "fovy": 45, "near": 0.5, "far": 5000}

``near``/``far`` are optional: without them the clip planes are fitted to the scene
(:func:`scene_clip`), as for the built-in paths, so a file written for a 100 km terrain is not
clipped at a fixed 10 km.

Positions and look-at points are interpolated with centripetal-free uniform Catmull-Rom
splines in time; orientations given directly are slerped. Built-in paths (``turn``, ``zoom``,
``forward``, ``orbit``, ``flyover``, ``walkthrough``) are fitted to a scene's axis-aligned
bounding box, +z up. ``walkthrough`` walks through a model at eye height (1.7 units above the
bottom of the box, or 30 % of the box height if that is lower), looking ahead: given the
scene's object boxes, along a way round them (:mod:`massview.lod.walk`), looking at the way
10 units ahead (a third of it, if that is less) and ending that far before its end; else along
x with a gentle sway in y. A scene's :class:`Footing` (:func:`massview.lod.walk.scene_footing`)
says what the walker stands on instead (a ground slab's top), how high its eye is (scaled in
a scene whose objects are far taller than a person: a model in millimetres) — the look ahead
scales with it — and whether there is ground to walk on at all: round a single object with
none, ``walkthrough`` walks and ``flyover`` flies an arc round it looking at it, framed
(:mod:`massview.core.framing`), so it is in every frame.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .camera import Camera, look_at_quaternion
from .errors import ConfigError
from .framing import direction, framed_camera, scene_clip

__all__ = ["BUILTIN_PATHS", "EYE_HEIGHT", "CameraPath", "Footing", "KeyframePath", "ParametricPath", "load_path", "scene_clip", "walk_eye_z"]

BUILTIN_PATHS = ("turn", "zoom", "forward", "orbit", "flyover", "walkthrough")
_LOOPS = ("turn", "orbit")  # closed: a full circle, t = 1 is t = 0


class CameraPath:
    fovy: float = 45.0

    def pose(self, t: float) -> tuple[np.ndarray, tuple]:  # pragma: no cover - abstract
        raise NotImplementedError

    def clip(self) -> tuple[float, float]:  # pragma: no cover - abstract
        raise NotImplementedError

    def camera(self, t: float, width: int, height: int) -> Camera:
        pos, q = self.pose(min(max(float(t), 0.0), 1.0))
        near, far = self.clip()
        return Camera(tuple(pos), q, fovy=self.fovy, near=near, far=far, width=width, height=height)

    def cameras(self, frames: int, width: int, height: int) -> list[Camera]:
        if frames < 1:
            raise ConfigError(f"--frames must be at least 1, got {frames}")
        ts = [0.0] if frames == 1 else [i / (frames - 1) for i in range(frames)]
        return [self.camera(t, width, height) for t in ts]


def _catmull_rom(points: np.ndarray, times: np.ndarray, t: float) -> np.ndarray:
    n = len(points)
    if n == 1:
        return points[0]
    i = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, n - 2))
    t0, t1 = times[i], times[i + 1]
    u = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
    p0 = points[max(i - 1, 0)]
    p1, p2 = points[i], points[i + 1]
    p3 = points[min(i + 2, n - 1)]
    u2, u3 = u * u, u * u * u
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 + (-p0 + 3 * p1 - 3 * p2 + p3) * u3)


def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
    else:
        th = math.acos(d)
        q = (math.sin((1 - u) * th) * q0 + math.sin(u * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)


@dataclass
class KeyframePath(CameraPath):
    times: np.ndarray
    positions: np.ndarray
    targets: np.ndarray | None
    orientations: np.ndarray | None
    fovy: float = 45.0
    near: float | None = None  # None: fitted to the scene by load_path (scene_clip)
    far: float | None = None
    source: str = field(default="keyframe path", compare=False)

    def clip(self):
        if self.near is None or self.far is None:
            raise ConfigError("keyframe path without near/far: load it with load_path(file, lo, hi) to fit them to the scene")
        return self.near, self.far

    def fit_clip(self, lo, hi) -> "KeyframePath":
        """Fill a missing ``near``/``far`` from the scene box and the keyframe positions."""
        near, far = scene_clip(lo, hi, self.positions)
        self.near = near if self.near is None else self.near
        self.far = far if self.far is None else self.far
        if not 0 < self.near < self.far:
            raise ConfigError(f"{self.source}: needs 0 < near < far, got near={self.near} far={self.far}")
        return self

    def pose(self, t):
        tt = self.times[0] + t * (self.times[-1] - self.times[0])
        pos = _catmull_rom(self.positions, self.times, tt)
        if self.targets is not None:
            target = _catmull_rom(self.targets, self.times, tt)
            return pos, look_at_quaternion(pos, target, heading=self._heading(tt, pos, target))
        i = int(np.clip(np.searchsorted(self.times, tt, side="right") - 1, 0, len(self.times) - 2))
        span = self.times[i + 1] - self.times[i] if len(self.times) > 1 else 1.0
        u = 0.0 if len(self.times) == 1 or span == 0 else (tt - self.times[i]) / span
        j = min(i + 1, len(self.times) - 1)
        return pos, tuple(_slerp(self.orientations[i], self.orientations[j], u))

    def _heading(self, tt: float, pos: np.ndarray, target: np.ndarray) -> np.ndarray | None:
        """Where the image's top points when the view at time ``tt`` is straight down or up
        (None otherwise): the level part of the view direction at the nearest time that has one
        (a little later first, then a little earlier, farther and farther), so a path through
        the nadir keeps the roll of its neighbouring frames instead of jumping to +y."""
        f = target - pos
        if np.hypot(f[0], f[1]) > 1e-9 * np.linalg.norm(f):
            return None
        span = float(self.times[-1] - self.times[0]) or 1.0
        for d in (1e-6, 1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0):
            for sign in (1.0, -1.0):
                t2 = min(max(tt + sign * d * span, self.times[0]), self.times[-1])
                g = _catmull_rom(self.targets, self.times, t2) - _catmull_rom(self.positions, self.times, t2)
                if np.hypot(g[0], g[1]) > 1e-6 * np.linalg.norm(g):
                    return np.array([g[0], g[1], 0.0])
        return None

    @classmethod
    def from_json(cls, data: dict, source: str = "<path>") -> "KeyframePath":
        kfs = data.get("keyframes")
        if not isinstance(kfs, list) or not kfs:
            raise ConfigError(f"{source}: expected a non-empty 'keyframes' list")
        for i, k in enumerate(kfs):  # each keyframe's vectors checked first, so a message names it
            if not isinstance(k, dict):
                raise ConfigError(f"{source}: keyframe {i} is not an object with 'time', 'position' and 'look_at'")
            for name, n in (("position", 3), ("look_at", 3), ("orientation", 4)):
                v = k.get(name)
                if v is None:
                    continue
                try:
                    ok = isinstance(v, list) and len(v) == n and all(math.isfinite(float(x)) for x in v)
                except (TypeError, ValueError):
                    ok = False
                if not ok:
                    raise ConfigError(f"{source}: keyframe {i}: {name!r} must be {n} finite numbers, got {v!r}")
            if "time" in k and not (isinstance(k["time"], (int, float)) and math.isfinite(k["time"])):
                raise ConfigError(f"{source}: keyframe {i}: 'time' must be a finite number, got {k['time']!r}")
            if "look_at" in k and "position" in k and [float(x) for x in k["look_at"]] == [float(x) for x in k["position"]]:
                raise ConfigError(f"{source}: keyframe {i}: 'look_at' equals 'position'; give a point the camera looks towards")
            if "orientation" in k and not any(float(x) for x in k["orientation"]):
                raise ConfigError(f"{source}: keyframe {i}: 'orientation' is all zeros; give a (w, x, y, z) quaternion")
        fovy = data.get("fovy", 45.0)
        if not (isinstance(fovy, (int, float)) and 0 < fovy < 180):
            raise ConfigError(f"{source}: 'fovy' must be a number of degrees between 0 and 180, got {fovy!r}")
        lacking = [i for i, k in enumerate(kfs) if "position" not in k]
        if lacking:
            raise ConfigError(f"{source}: keyframe {lacking[0]} has no 'position' [x, y, z]")
        if not all("look_at" in k for k in kfs) and not all("orientation" in k for k in kfs):
            i = next(i for i, k in enumerate(kfs) if "look_at" not in k)
            raise ConfigError(f"{source}: keyframe {i} has no 'look_at' [x, y, z] (or give every keyframe an 'orientation' "
                              "[w, x, y, z] quaternion instead)")
        try:
            times = np.array([float(k.get("time", i)) for i, k in enumerate(kfs)])
            positions = np.array([[float(v) for v in k["position"]] for k in kfs])
            if all("look_at" in k for k in kfs):
                targets = np.array([[float(v) for v in k["look_at"]] for k in kfs])
                orients = None
            else:
                targets = None
                orients = np.array([[float(v) for v in k["orientation"]] for k in kfs])
                orients /= np.linalg.norm(orients, axis=1, keepdims=True)
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"{source}: malformed keyframe ({e}); each needs 'time', 'position' [x,y,z] and 'look_at' [x,y,z]") from None
        if positions.shape[1:] != (3,) or np.any(np.diff(times) < 0):
            raise ConfigError(f"{source}: positions must be [x, y, z] and times non-decreasing")
        try:
            near, far = (None if data.get(k) is None else float(data[k]) for k in ("near", "far"))
        except (TypeError, ValueError):
            raise ConfigError(f"{source}: 'near' and 'far' must be numbers (world units)") from None
        return cls(times, positions, targets, orients, float(fovy), near, far, source)


@dataclass(frozen=True)
class Footing:
    """Where ``walkthrough`` walks in a polygon scene: on ``ground`` (world z: a floor's top, or
    the box's bottom), the eye ``eye`` units above it; ``walkable`` False where nothing is there
    to walk on or among (a single object: ``walkthrough`` and ``flyover`` go round it instead).
    Made from the objects' boxes by :func:`massview.lod.walk.scene_footing`."""

    ground: float
    eye: float
    walkable: bool = True

    def __post_init__(self):
        if not (math.isfinite(self.ground) and math.isfinite(self.eye) and self.eye >= 0):  # (0: a flat box's)
            raise ConfigError(f"Footing needs a finite ground and eye height >= 0, got {self.ground}, {self.eye}")

    @classmethod
    def of_box(cls, lo, hi) -> "Footing":
        """What a box alone says: the box's bottom, :func:`walk_eye_z` above it."""
        return cls(float(lo[2]), walk_eye_z(lo, hi) - float(lo[2]))


@dataclass
class ParametricPath(CameraPath):
    """One of the built-in paths, fitted to the box ``lo``..``hi`` (world units, +z up).
    ``route``: xy waypoints (k, 2) that ``walkthrough`` walks along at eye height (planned round
    a scene's objects by :func:`massview.lod.walk.plan_walk`); without one it walks the straight
    swaying line. ``ground`` (xy (n, 2) → z (n,), :func:`massview.lod.walk.terrain_ground`):
    the surface ``walkthrough`` walks on — a terrain's — instead of the box's bottom.
    ``footing`` (:class:`Footing`): a polygon scene's ground, eye height and whether it has
    ground to walk on (``walkthrough`` and ``flyover``); None: :meth:`Footing.of_box`."""

    name: str
    lo: np.ndarray
    hi: np.ndarray
    fovy: float = 45.0
    route: np.ndarray | None = field(default=None, compare=False, repr=False)
    ground: Callable | None = field(default=None, compare=False, repr=False)
    footing: Footing | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if self.name not in BUILTIN_PATHS:
            raise ConfigError(f"unknown path {self.name!r}; use one of {', '.join(BUILTIN_PATHS)} or a .json keyframe file")
        self.lo = np.asarray(self.lo, np.float64)
        self.hi = np.asarray(self.hi, np.float64)
        if self.footing is None:
            self.footing = Footing.of_box(self.lo, self.hi)

    @property
    def _round(self) -> bool:
        """``walkthrough`` or ``flyover`` round a scene with no ground to walk on (framed arcs)."""
        return self.name in ("walkthrough", "flyover") and not self.footing.walkable and self.ground is None

    @property
    def _size(self) -> float:
        return float(max(np.linalg.norm((self.hi - self.lo)[:2]), 1e-9))

    def clip(self):
        near, far = scene_clip(self.lo, self.hi)
        if self.name == "walkthrough" and self.ground is not None:  # 1.7 units above a surface that reaches
            near = min(near, 0.25 * EYE_HEIGHT)                   # up to the eye's feet: the near plane inside
        return near, far                                          # the eye height, not 2e-4 of the whole box

    def cameras(self, frames: int, width: int, height: int) -> list[Camera]:
        """As :meth:`CameraPath.cameras`, except that the closed loops (``turn``, ``orbit``: a
        full circle, t = 1 is t = 0) take ``frames`` steps of 1/frames round it, so no view comes
        twice (with t = i/(frames − 1) a 2-frame orbit rendered one view twice, and a looped
        video of the default 10 repeated its first frame)."""
        if self.name not in _LOOPS or frames < 1:
            return super().cameras(frames, width, height)
        return [self.camera(i / frames, width, height) for i in range(frames)]

    def camera(self, t: float, width: int, height: int) -> Camera:
        """As :meth:`CameraPath.camera`; ``orbit`` keeps its direction to the scene's middle but
        stands back just far enough that all 8 corners of the box are in view, with a 5 % margin,
        for this image's aspect (at 0.75 of the box's width it cut off the near corners of a
        square terrain, and more of a long scene), its near plane just before the box (depth
        stays precise: at 2e-4 of the diagonal, far/near was ~20000); so do ``walkthrough``
        and ``flyover`` round a scene with no ground (:meth:`_round_direction`)."""
        t = min(max(float(t), 0.0), 1.0)
        if self.name == "orbit":
            v = self.pose(t)[0] - (self.lo + self.hi) / 2  # from the middle towards the eye
        elif self._round:
            v = self._round_direction(t)
        else:
            return super().camera(t, width, height)
        return framed_camera(self.lo, self.hi, v, width, height, self.fovy, centred=self.name != "orbit")

    def _round_direction(self, t: float) -> np.ndarray:
        """From the middle towards the eye, round a scene with nothing to walk on: ``walkthrough``
        walks a third of a circle in front of it (azimuth −150° to −30°) a little above its
        middle (12°); ``flyover`` sweeps from the front-left to the back-right (−160° to 20°)
        rising to 60° above it halfway."""
        if self.name == "walkthrough":
            return direction(-150.0 + 120.0 * t, 12.0)
        return direction(-160.0 + 180.0 * t, 20.0 + 40.0 * math.sin(math.pi * t))

    def pose(self, t):
        c = (self.lo + self.hi) / 2
        ext = self.hi - self.lo
        top = self.hi[2]
        s = self._size
        if self.name == "turn":  # stand above the middle, turn a full circle, looking down-out
            eye = np.array([c[0], c[1], top + 0.02 * s])
            a = 2 * math.pi * t
            tgt = eye + np.array([math.cos(a), math.sin(a), -0.12]) * s * 0.3
        elif self.name == "zoom":  # descend toward the middle along an oblique line
            far = np.array([c[0] - 0.6 * ext[0], c[1] - 0.6 * ext[1], top + 0.9 * s])
            near = np.array([c[0] - 0.05 * ext[0], c[1] - 0.05 * ext[1], top + 0.006 * s])
            u = t * t * (3 - 2 * t)
            eye = far + (near - far) * u
            tgt = np.array([c[0] + 0.05 * ext[0], c[1] + 0.05 * ext[1], c[2]])
        elif self.name == "forward":  # fly straight along +x at low altitude
            x = self.lo[0] + ext[0] * (0.05 + 0.7 * t)
            eye = np.array([x, c[1], top + 0.015 * s])
            tgt = eye + np.array([1.0, 0.0, -0.12]) * s * 0.2
        elif self.name == "orbit":  # circle the whole scene looking at its middle
            a = 2 * math.pi * t
            r = 0.75 * s
            eye = np.array([c[0] + r * math.cos(a), c[1] + r * math.sin(a), top + 0.35 * s])
            tgt = c
        elif self._round:
            eye = (self.lo + self.hi) / 2 + self._round_direction(t) * s
            tgt = (self.lo + self.hi) / 2
        elif self.name == "walkthrough":
            eye, tgt = self._walk(t)
        else:  # flyover: a curved low pass across the scene, looking ahead and down
            def at(u):
                x = self.lo[0] + ext[0] * (0.1 + 0.8 * u)
                y = c[1] + 0.3 * ext[1] * math.sin(2 * math.pi * u)
                z = top + s * (0.012 + 0.008 * math.cos(2 * math.pi * u))
                return np.array([x, y, z])
            eye = at(t)
            ahead = at(min(t + 0.05, 1.0)) if t < 0.95 else eye + (eye - at(t - 0.05))
            d = ahead - eye
            d[2] = 0
            d /= max(np.linalg.norm(d), 1e-12)
            tgt = eye + d * s * 0.2 + np.array([0, 0, -0.035 * s])
            if self.hi[2] - c[2] > 0.1 * s:  # relief deeper than ~20 % of the size (a strongly exaggerated one):
                tgt[2] = min(tgt[2], c[2])  # look down to its middle height (ahead at the top, the frame was all sky)
        return eye, look_at_quaternion(eye, tgt)

    def _route(self):
        """(waypoints (k, 2), their cumulative length (k,)) of the given route, None without one."""
        way = None if self.route is None else np.asarray(self.route, np.float64).reshape(-1, 2)
        if way is None or len(way) < 2:
            return None
        return way, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(way, axis=0), axis=1))])

    def _walk(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Eye height through the scene, looking ahead (slightly down): along the route at
        constant speed, else along x swaying in y."""
        if self.ground is not None:  # on a terrain: eye height above the ground under the eye
            return self._walk_ground(t)
        ext = self.hi - self.lo
        z = self.footing.ground + self.footing.eye
        look = _WALK_LOOK * max(self.footing.eye, EYE_HEIGHT) / EYE_HEIGHT  # 10 units ahead, more for a walker scaled up
        route = self._route()
        if route is not None:
            return self._walk_route(t, *route, z, look)

        def at(u):
            return np.array([self.lo[0] + ext[0] * (0.08 + 0.84 * u),
                             (self.lo[1] + self.hi[1]) / 2 + 0.12 * ext[1] * math.sin(2 * math.pi * u), z])

        eye = at(t)
        d = at(min(t + 0.02, 1.0)) - at(max(t - 0.02, 0.0))
        d /= max(np.linalg.norm(d), 1e-12)
        return eye, eye + d * look + np.array([0.0, 0.0, -_WALK_DIP * look])

    @staticmethod
    def _walk_route(t: float, way: np.ndarray, s: np.ndarray, z: float, look: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
        """``walkthrough`` along a planned way (xy (k, 2), cumulative length ``s``) at height
        ``z``: looking at the way ``look`` ahead (``_WALK_LOOK`` units for a 1.7-unit walker, at
        most a third of the way, so a small scene's walker looks across the scene, not half out
        of it), a little down; the eye walks the way's first ``length − look``, so its last view
        is along the way to the way's end, not out of the scene from the end."""
        look = min(look, s[-1] / 3)

        def at(d):
            return np.array([np.interp(d, s, way[:, 0]), np.interp(d, s, way[:, 1]), z])

        d = t * (s[-1] - look)
        eye, ahead = at(d), at(d + look)
        return eye, ahead - np.array([0.0, 0.0, _WALK_DIP * float(np.linalg.norm(ahead - eye))])

    def _walk_ground(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``walkthrough`` on a terrain: along the straight swaying line at eye height above the
        ground under each point, looking ``_LOOK`` units ahead, a little down, and up or down by
        half the ground's slope there (as a walker does: level on the flat, up a rise without
        staring into it, down a descent without looking at the sky)."""
        ext = self.hi - self.lo
        span = 0.84 * ext[0]

        def xy(u):
            u = min(max(u, 0.0), 1.0)
            return np.array([self.lo[0] + ext[0] * (0.08 + 0.84 * u),
                             (self.lo[1] + self.hi[1]) / 2 + 0.12 * ext[1] * math.sin(2 * math.pi * u)])

        p = xy(t)
        d = xy(t + 0.02) - xy(t - 0.02)
        d /= max(np.linalg.norm(d), 1e-12)
        look = min(_LOOK, 0.05 * span) if span > 0 else _LOOK
        ahead = p + d * look
        gz = self.ground(np.stack([p, ahead]))
        eye = np.array([p[0], p[1], gz[0] + EYE_HEIGHT])
        tgt = np.array([ahead[0], ahead[1], eye[2] + 0.5 * (gz[1] - gz[0]) - 0.6])
        return eye, tgt


EYE_HEIGHT = 1.7  # walkthrough's eye height above the ground (world units: metres for georeferenced data)
_WALK_LOOK = 10.0  # how far ahead a walker in a scene looks (world units; at most a third of a planned way)
_WALK_DIP = 0.06  # and how far down, per unit ahead
_LOOK = 30.0  # how far ahead a walker on a terrain looks (world units)


def exaggerated_box(lo, hi, exaggeration: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A terrain's world box ``lo..hi`` (at 1×) as drawn at ``exaggeration``: heights scaled about
    the lowest one (T1's and T2's ``base + e·(z − base)``), so the top rises and the bottom stays.
    The box the built-in paths and clip planes are fitted to at that exaggeration."""
    lo, hi = np.array(lo, np.float64), np.array(hi, np.float64)
    hi[2] = lo[2] + float(exaggeration) * (hi[2] - lo[2])
    return lo, hi


def walk_eye_z(lo, hi) -> float:
    """``walkthrough``'s eye height: 1.7 units above the box's bottom, or 30 % of its height
    if that is lower."""
    return float(lo[2]) + min(EYE_HEIGHT, 0.3 * (float(hi[2]) - float(lo[2])))


def load_path(spec: str, lo, hi, route: np.ndarray | None = None, ground: Callable | None = None,
              footing: Footing | None = None) -> CameraPath:
    """A built-in path name fitted to the box lo..hi, or a keyframe ``.json`` file (its missing
    clip planes fitted to the box). ``route`` (xy waypoints, :func:`massview.lod.walk.plan_walk`):
    the way ``walkthrough`` walks; ``ground`` (a terrain's surface,
    :func:`massview.lod.walk.terrain_ground`): what it walks on; ``footing`` (a polygon scene's,
    :func:`massview.lod.walk.scene_footing`): what ``walkthrough`` stands on and how high, and
    whether ``walkthrough`` and ``flyover`` go round the scene instead
    (:func:`massview.lod.walk.fit_path` gives all three as the scene has them)."""
    if spec in BUILTIN_PATHS:
        walk = spec == "walkthrough"
        return ParametricPath(spec, lo, hi, route=route if walk else None, ground=ground if walk else None,
                              footing=footing if spec in ("walkthrough", "flyover") else None)
    p = Path(spec)
    if p.suffix.lower() != ".json":
        raise ConfigError(f"--path {spec!r}: use one of {', '.join(BUILTIN_PATHS)} or a .json keyframe file")
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"--path {spec}: file not found") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"--path {spec}: not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"--path {spec}: expected a JSON object with a 'keyframes' list")
    return KeyframePath.from_json(data, source=str(p)).fit_clip(lo, hi)
