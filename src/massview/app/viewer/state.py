"""What the browser controls: a fly camera and the render settings, validated strictly.

Messages (JSON text, at most 64 KiB):

* ``{"type": "input", "move": [forward, right, up], "look": [dx, dy], "wheel": n, "dt": s}`` —
  move components in [-1, 1], look deltas in pixels (|d| ≤ 4000), wheel steps (|n| ≤ 20),
  dt in (0, 1] seconds;
* ``{"type": "settings", "decomposition": str, "compositor": str, "tau": float,
  "color_by_rank": bool, "exaggeration": float, "sun": [azimuth, altitude], "colormap": str,
  "haze": float}`` — any subset; values from the lists the server announced (terrain shading:
  exaggeration in [0.1, 20], azimuth in [0, 360], altitude in [0, 90] degrees, haze in [0, 10]);
* anything else is rejected with a reason (and logged by the server).
"""

from __future__ import annotations

import json
import math
import threading

import numpy as np

from ...core.camera import Camera, look_at_quaternion

__all__ = ["ViewerState", "MessageError", "MAX_MESSAGE", "VIEWER_COLORMAPS"]

MAX_MESSAGE = 64 * 1024
VIEWER_COLORMAPS = ("auto", "hypsometric", "ortho", "none", "terrain", "gist_earth", "cividis", "viridis", "gray")


class MessageError(ValueError):
    pass


def _num(v, lo, hi, what):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        raise MessageError(f"{what} must be a number in [{lo}, {hi}]")
    return float(v)


class ViewerState:
    """The browser's camera and settings. ``relief``: a terrain's world box at exaggeration 1
    (lo, hi); a new exaggeration then moves the eye with the relief (heights scale about the
    lowest one, ``base + e·(z − base)``, the eye's height too, so it keeps its place over the
    ground instead of ending under it), turns its view direction with the same vertical
    stretch (so it looks at the same point of the relief) and refits the far plane to the box
    as drawn."""

    def __init__(self, start: Camera, settings: dict, choices: dict, base_speed: float, relief: tuple | None = None):
        self._lock = threading.Lock()
        self.relief = None if relief is None else tuple(np.asarray(v, np.float64) for v in relief)
        self.pos = np.array(start.position)
        f = start.forward
        self.yaw = math.atan2(f[1], f[0])
        self.pitch = math.asin(max(-1.0, min(1.0, f[2])))
        self.template = start
        self.speed = base_speed
        self.base_speed = base_speed
        self.settings = dict(settings)
        self.choices = choices  # name -> allowed values
        self.stop = False
        self.rejected = 0

    def camera(self) -> Camera:
        with self._lock:
            d = np.array([math.cos(self.pitch) * math.cos(self.yaw), math.cos(self.pitch) * math.sin(self.yaw), math.sin(self.pitch)])
            return self.template.replace(position=tuple(self.pos), orientation=look_at_quaternion(self.pos, self.pos + d))

    def snapshot(self) -> dict:
        cam = self.camera()
        with self._lock:
            return {"camera": cam, "settings": dict(self.settings), "stop": self.stop}

    def apply(self, raw) -> str:
        """Apply one client message; returns its type or raises MessageError."""
        if isinstance(raw, (bytes, bytearray)):
            raise MessageError("binary messages are not accepted")
        if len(raw) > MAX_MESSAGE:
            raise MessageError(f"message of {len(raw)} bytes is over {MAX_MESSAGE}")
        try:
            msg = json.loads(raw)
        except (json.JSONDecodeError, RecursionError) as e:
            raise MessageError(f"not JSON ({e})") from None
        if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
            raise MessageError("expected an object with a 'type'")
        kind = msg["type"]
        if kind == "input":
            self._input(msg)
        elif kind == "settings":
            self._settings(msg)
        else:
            raise MessageError(f"unknown message type {kind[:40]!r}")
        return kind

    def _input(self, msg: dict) -> None:
        move = msg.get("move", [0, 0, 0])
        look = msg.get("look", [0, 0])
        if not (isinstance(move, list) and len(move) == 3 and isinstance(look, list) and len(look) == 2):
            raise MessageError("input needs move [f, r, u] and look [dx, dy]")
        f, r, u = (_num(v, -1, 1, "move") for v in move)
        dx, dy = (_num(v, -4000, 4000, "look") for v in look)
        wheel = _num(msg.get("wheel", 0), -20, 20, "wheel")
        dt = _num(msg.get("dt", 0.0), 0, 1, "dt")
        with self._lock:
            self.yaw -= dx * 0.003
            self.pitch = max(-1.5, min(1.5, self.pitch - dy * 0.003))
            self.speed = max(self.base_speed / 100, min(self.base_speed * 100, self.speed * 1.25 ** (-wheel)))
            fwd = np.array([math.cos(self.pitch) * math.cos(self.yaw), math.cos(self.pitch) * math.sin(self.yaw), math.sin(self.pitch)])
            right = np.array([math.sin(self.yaw), -math.cos(self.yaw), 0.0])
            self.pos = self.pos + (fwd * f + right * r + np.array([0, 0, 1.0]) * u) * self.speed * dt

    def _follow_relief(self, e0: float, e1: float) -> None:
        """The eye's height from exaggeration ``e0`` to ``e1`` (see the class docstring)."""
        from ...core.framing import scene_clip
        from ...core.paths import exaggerated_box

        if e1 == e0:
            return
        base, k = float(self.relief[0][2]), e1 / e0
        with self._lock:  # the eye and the direction it looks in, stretched with the world (walk8 L3: the pitch kept,
            self.pos = np.array([self.pos[0], self.pos[1], base + (self.pos[2] - base) * k])  # it looked over the relief)
            self.pitch = max(-1.5, min(1.5, math.atan2(k * math.sin(self.pitch), math.cos(self.pitch))))
            _, far = scene_clip(*exaggerated_box(*self.relief, e1), self.pos[None])
            self.template = self.template.replace(far=max(far, self.template.near * 2))

    def _settings(self, msg: dict) -> None:
        new = {}
        for key in ("decomposition", "compositor"):
            if key in msg:
                if msg[key] not in self.choices[key]:
                    raise MessageError(f"{key} must be one of {', '.join(self.choices[key])}")
                new[key] = msg[key]
        if "tau" in msg:
            new["tau"] = _num(msg["tau"], 0.25, 16, "tau")
        if "color_by_rank" in msg:
            if not isinstance(msg["color_by_rank"], bool):
                raise MessageError("color_by_rank must be true or false")
            new["color_by_rank"] = msg["color_by_rank"]
        new.update(self._shading(msg))
        unknown = set(msg) - {"type", "decomposition", "compositor", "tau", "color_by_rank", "exaggeration", "sun", "colormap", "haze"}
        if unknown:
            raise MessageError(f"unknown setting(s) {', '.join(sorted(unknown))[:80]}")
        if "exaggeration" in new and self.relief is not None:
            self._follow_relief(float(self.settings.get("exaggeration", 1.0)), new["exaggeration"])
        with self._lock:
            self.settings.update(new)

    def _shading(self, msg: dict) -> dict:
        new = {}
        if "exaggeration" in msg:
            new["exaggeration"] = _num(msg["exaggeration"], 0.1, 20, "exaggeration")
        if "haze" in msg:
            new["haze"] = _num(msg["haze"], 0, 10, "haze")
        if "sun" in msg:
            sun = msg["sun"]
            if not (isinstance(sun, list) and len(sun) == 2):
                raise MessageError("sun must be [azimuth, altitude] in degrees")
            new["sun"] = [_num(sun[0], 0, 360, "sun azimuth"), _num(sun[1], 0, 90, "sun altitude")]
        if "colormap" in msg:
            if msg["colormap"] not in self.choices.get("colormap", ()):
                raise MessageError(f"colormap must be one of {', '.join(self.choices.get('colormap', ()))}")
            new["colormap"] = msg["colormap"]
        return new

    def request_stop(self) -> None:
        with self._lock:
            self.stop = True

    def position(self) -> list[float]:
        with self._lock:
            return [round(float(v), 2) for v in self.pos]
