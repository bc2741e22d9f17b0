"""Client-side visibility bookkeeping of the massive-model system (Revanth & Narayanan 2012, §3.5).

Per frame, a client's objects in its sub-frustum fall into:

* **depth pass** — the potential occluders and the previous frame's visible objects still in
  the sub-frustum: drawn to depth before any query;
* **near** — objects whose box reaches in front of the near plane (in particular boxes that
  contain the eye): a box query cannot be trusted there (clipped faces), so they are visible
  without a query;
* **marked** — objects that passed a query in the last ``n`` frames (``--visible-frames n``):
  visible without a query until the mark runs out, then re-tested in their n-th frame if
  they are still in the sub-frustum;
* **query** — every other object: tested with a hardware occlusion query on its box.

The visible list handed to the renderer is occluders ∪ near ∪ marked ∪ passed queries; it
becomes the next frame's "previous visible" set. :class:`VisibilityState` holds the marks
(one int64 per object: the last frame its mark covers) — plain numpy, no GL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera
from ..core.errors import ConfigError

__all__ = ["VisibilityPlan", "VisibilityState", "boxes_reach_near"]


@dataclass(frozen=True)
class VisibilityPlan:
    """One frame's split of a client's objects (sorted int64 object ids, disjoint except
    ``depth_pass``, which overlaps the others)."""

    frame: int
    items: np.ndarray
    depth_pass: np.ndarray
    occluders: np.ndarray
    near: np.ndarray
    marked: np.ndarray
    query: np.ndarray


def boxes_reach_near(camera: Camera, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(n,) bool: some corner of the world box ``[lo, hi]`` lies closer than the near plane
    (depth along the view direction < near) — including every box that contains the eye."""
    lo = np.asarray(lo, np.float64).reshape(-1, 3)
    hi = np.asarray(hi, np.float64).reshape(-1, 3)
    f = camera.forward
    eye = np.asarray(camera.position)
    nearest = np.where(f >= 0, lo, hi)  # the corner with the least depth
    return (nearest - eye) @ f < camera.near


class VisibilityState:
    """Visible marks and the previous frame's visible set of one client.

    n_objects: objects in the scene (ids index per-object arrays); frames: ``n`` of §3.5,
    how many frames a passed query keeps an object visible (1 = re-test every frame)."""

    def __init__(self, n_objects: int, frames: int = 4):
        if frames < 1:
            raise ConfigError(f"--visible-frames must be at least 1, got {frames}")
        self.frames = int(frames)
        self.until = np.full(int(n_objects), -1, np.int64)  # last frame the mark covers
        self.previous = np.zeros(0, np.int64)

    def plan(self, frame: int, items: np.ndarray, occluder: np.ndarray, near: np.ndarray | None = None) -> VisibilityPlan:
        """items: object ids in the sub-frustum; occluder: (n_objects,) bool flags;
        near: (len(items),) bool from :func:`boxes_reach_near` (None: none)."""
        items = np.unique(np.asarray(items, np.int64))
        occ = items[occluder[items]]
        near_ids = items[np.asarray(near, bool)] if near is not None else np.zeros(0, np.int64)
        near_ids = np.setdiff1d(near_ids, occ, assume_unique=True)
        rest = np.setdiff1d(items, np.union1d(occ, near_ids), assume_unique=True)
        marked = rest[self.until[rest] >= frame]
        query = rest[self.until[rest] < frame]
        depth_pass = np.union1d(occ, np.intersect1d(self.previous, items, assume_unique=True))
        return VisibilityPlan(int(frame), items, depth_pass, occ, near_ids, marked, query)

    def finish(self, plan: VisibilityPlan, passed: np.ndarray) -> np.ndarray:
        """Record the query results (``passed``: bool per ``plan.query``) and return the
        frame's visible list (sorted ids): occluders ∪ near ∪ marked ∪ passed."""
        passed = np.asarray(passed, bool)
        if passed.shape != plan.query.shape:
            raise ValueError(f"{passed.shape[0]} query results for {plan.query.shape[0]} queries")
        won = plan.query[passed]
        self.until[won] = plan.frame + self.frames - 1
        visible = np.union1d(np.union1d(plan.occluders, plan.near), np.union1d(plan.marked, won))
        self.previous = visible
        return visible
