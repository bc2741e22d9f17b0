"""Hierarchical occlusion queries over the scene's group tree (M1's visibility module, §3.5).

The paper replaces every geode of the scenegraph by an occlusion-query node, so each object of
the sub-frustum that is not an occluder, not marked and not just seen is tested with its own
query on its bounding box. On Mesa llvmpipe a query costs ~30 µs (the begin/end pair and the
box raster), and a client of the 4-plant bench issues ~2 900 a frame. :class:`GroupQueries`
finds **the same visible set** with fewer queries by testing the query objects through the
skeleton's hierarchy (the group tree the server frustum-culls with), in the manner of
coherent hierarchical culling (Bittner et al. 2004):

* every group gets the box of the *query objects* below it (the union of their boxes — not
  the group's whole box: occluders, marked and out-of-frustum objects are left out), widened
  by half a pixel at its farthest corner so that rasterization ties on shared faces and
  silhouette edges always fall inside the group's box;
* the tree is walked down in rounds. In a round, each group of the frontier is either
  *queried* or *opened* without a query: opened when it has fewer than two parts (child groups
  with query objects below, plus its own query objects: its box is then its one part's box),
  when its box reaches in front of the near plane (a clipped box is no test), or — coherence —
  when it was found visible on the previous frame (it would most likely pass again). The
  query objects of an opened group are queried in the same round. A queried group that
  passes is opened in the next round; one that fails culls every query object below it,
  unqueried;
* each round is one batch of queries and one blocking wait for its results: a frame waits at
  most (tree depth + 1) times, never once per object.

Why the result equals the flat per-object test (so culling stays conservative, as there): an
object's box lies inside every ancestor's box. A pixel covered by the object's box is covered
by the ancestor's box, whose front face is no farther along the pixel's ray; and a box's back
face can pass the depth test only where its front face does. With ``s`` the samples a box
passes (front and back faces are both drawn), s(object) ≤ 2 · s(ancestor). A group is
therefore culled only when 2 · s(group) ≤ threshold: then every object below it has
s(object) ≤ threshold and would fail its own query.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["HierarchyResult", "GroupQueries", "box_screen_area", "widen_boxes"]


def widen_boxes(lo: np.ndarray, hi: np.ndarray, eye: np.ndarray, pixel: float) -> tuple[np.ndarray, np.ndarray]:
    """World boxes ((k, 3) float64) widened on every side by half a pixel at their farthest
    corner from ``eye`` (``pixel``: world size of a pixel at distance 1): the box then strictly
    encloses what it bounds on screen and in depth, so depth ties with a coplanar occluder and
    rasterization ties on edges fall on the visible side."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    far = np.maximum(np.abs(lo - eye), np.abs(hi - eye))
    pad = (0.5 * pixel) * np.sqrt((far * far).sum(-1))[..., None]
    return lo - pad, hi + pad


def box_screen_area(camera, vp, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(k,) float64 pixels of viewport ``vp`` covered by the bounding rectangle of each world
    box's projection (``lo``/``hi`` (k, 3)) in ``camera``'s full image; a box with a corner
    behind the eye counts as the whole viewport."""
    W, H = camera.width, camera.height
    to_pixels = np.array([[W / 2, 0, 0, W / 2], [0, -H / 2, 0, H / 2], [0, 0, 1, 0], [0, 0, 0, 1]])  # top-left origin
    mvp = to_pixels @ camera.view_projection()
    x0, y0, x1, y1 = vp.x, vp.y, vp.x + vp.w, vp.y + vp.h
    lo, hi = np.asarray(lo, np.float64).reshape(-1, 3), np.asarray(hi, np.float64).reshape(-1, 3)
    corners = np.where(_CORNERS[None, :, :], hi[:, None, :], lo[:, None, :])  # (k, 8, 3)
    clip = corners @ mvp[:3, :3].T + mvp[:3, 3]
    w = corners @ mvp[3, :3] + mvp[3, 3]
    behind = (w <= 1e-9).any(1)
    w = np.where(w > 1e-9, w, 1.0)
    sx, sy = clip[..., 0] / w, clip[..., 1] / w
    full = (x1 - x0) * (y1 - y0)
    ax0 = np.clip(sx.min(1), x0, x1)
    ax1 = np.clip(sx.max(1), x0, x1)
    ay0 = np.clip(sy.min(1), y0, y1)
    ay1 = np.clip(sy.max(1), y0, y1)
    return np.where(behind, full, (ax1 - ax0) * (ay1 - ay0))


_CORNERS = np.array([[(c >> k) & 1 for k in range(3)] for c in range(8)], bool)


@dataclass(frozen=True)
class HierarchyResult:
    """One frame's hierarchical test of the query objects (in the order given).

    samples: (n,) int64 samples of the object's own box, or of the culling ancestor's box for
    objects culled by a group; passed: (n,) bool visible; group_queries / object_queries:
    queries issued on group boxes and on object boxes; culled_by_group: objects culled by a
    hidden ancestor without a query; rounds: batches issued (= blocking waits)."""

    samples: np.ndarray
    passed: np.ndarray
    group_queries: int
    object_queries: int
    culled_by_group: int
    rounds: int

    @property
    def issued(self) -> int:
        return self.group_queries + self.object_queries


class GroupQueries:
    """The traversal state of one client: the group tree (``parent`` (g,) int, −1 for roots;
    ``depth`` (g,) int) and each object's group ``obj_group`` (n,).

    ``coherent``: open groups found visible on the previous frame without a query."""

    def __init__(self, parent: np.ndarray, depth: np.ndarray, obj_group: np.ndarray, coherent: bool = True):
        self.parent = np.asarray(parent, np.int64)
        self.depth = np.asarray(depth, np.int64)
        self.obj_group = np.asarray(obj_group, np.int64)
        self.coherent = bool(coherent)
        self.seen = np.zeros(0, np.int64)  # sorted groups with a visible query object last frame

    def ancestors(self, groups: np.ndarray) -> np.ndarray:
        """Sorted unique ``groups`` and all their ancestors (global ids)."""
        mark = np.zeros(len(self.parent), bool)
        cur = np.asarray(groups, np.int64)
        while len(cur):
            cur = cur[~mark[cur]]
            mark[cur] = True
            cur = self.parent[cur]
            cur = cur[cur >= 0]
        return np.flatnonzero(mark)

    def run(self, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray, query: Callable[[np.ndarray, np.ndarray], np.ndarray],
            near: Callable[[np.ndarray, np.ndarray], np.ndarray], threshold: int, eye: np.ndarray, pixel: float,
            area: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> HierarchyResult:
        """Test objects ``ids`` ((n,) int) with world boxes ``lo``/``hi`` ((n, 3) float64).

        query(lo, hi) -> (k,) int64 samples of k boxes (one batch, one wait); near(lo, hi) ->
        (k,) bool, the boxes reaching in front of the near plane; threshold: an object passes
        with more samples; eye: the camera position; pixel: the world size of one pixel at
        distance 1 (2 tan(fovy/2) / image height), for widening group boxes by half a pixel;
        area(lo, hi) -> (k,) pixels the boxes cover on screen (:func:`box_screen_area`): a group
        whose box covers more than its parts together is opened without a query."""
        ids = np.asarray(ids, np.int64)
        lo, hi = np.asarray(lo, np.float64).reshape(-1, 3), np.asarray(hi, np.float64).reshape(-1, 3)
        samples = np.full(len(ids), -1, np.int64)
        if len(ids) == 0:
            return HierarchyResult(samples, np.zeros(0, bool), 0, 0, 0, 0)
        t = _Tree(self, lo, hi, ids)
        g_lo, g_hi = t.widened(np.asarray(eye, np.float64), pixel)
        skip = np.isin(t.act, self.seen) if self.coherent else np.zeros(len(t.act), bool)
        if area is not None:
            skip |= t.wide(area(g_lo, g_hi), area(lo, hi))
        frontier, objects = t.roots, np.zeros(0, np.int64)
        gq = oq = rounds = 0
        dead = np.full(len(t.act), -1, np.int64)  # samples of a culled group
        while len(frontier) or len(objects):
            ask, more = t.open_free(frontier, g_lo, g_hi, near, skip)
            objects = np.concatenate([objects, more])
            if len(ask) == 0 and len(objects) == 0:
                break
            s = query(np.concatenate([g_lo[ask], lo[objects]]), np.concatenate([g_hi[ask], hi[objects]]))
            rounds, gq, oq = rounds + 1, gq + len(ask), oq + len(objects)
            samples[objects] = s[len(ask):]
            hidden = 2 * s[:len(ask)] <= threshold
            dead[ask[hidden]] = s[:len(ask)][hidden]
            frontier, objects = t.children(ask[~hidden]), t.own_objects(ask[~hidden])
        culled = samples < 0
        samples[culled] = t.inherit(dead)[t.leaf[culled]]
        passed = ~culled & (samples > threshold)
        self.seen = self.ancestors(self.obj_group[ids[passed]])
        return HierarchyResult(samples, passed, gq, oq, int(culled.sum()), rounds)


class _Tree:
    """One frame's part of the tree: the groups with query objects below them (``act``,
    sorted global ids; everything else indexes into it), their union boxes and parts."""

    def __init__(self, gq: GroupQueries, lo: np.ndarray, hi: np.ndarray, ids: np.ndarray):
        leaf = gq.obj_group[ids]
        self.act = act = gq.ancestors(leaf)
        m = len(act)
        self.leaf = np.searchsorted(act, leaf)
        p = gq.parent[act]
        self.parent = np.where(p >= 0, np.searchsorted(act, p), -1)
        depth = gq.depth[act]
        self.by_depth = [np.flatnonzero(depth == d) for d in range(int(depth.max()) + 1)]
        order = np.argsort(self.parent, kind="stable")
        self.child = order[self.parent[order] >= 0]  # sorted by parent
        self.child_parent = self.parent[self.child]
        self.roots = order[self.parent[order] < 0]
        self.obj_order = np.argsort(self.leaf, kind="stable")  # query positions sorted by group
        self.obj_leaf = self.leaf[self.obj_order]
        own = np.bincount(self.leaf, minlength=m)
        self.g_lo = np.full((m, 3), np.inf)
        self.g_hi = np.full((m, 3), -np.inf)
        np.minimum.at(self.g_lo, self.leaf, lo)
        np.maximum.at(self.g_hi, self.leaf, hi)
        for level in reversed(self.by_depth[1:]):  # children before parents: pull the boxes up
            np.minimum.at(self.g_lo, self.parent[level], self.g_lo[level])
            np.maximum.at(self.g_hi, self.parent[level], self.g_hi[level])
        self.parts = own + np.bincount(self.child_parent, minlength=m)

    def widened(self, eye: np.ndarray, pixel: float) -> tuple[np.ndarray, np.ndarray]:
        """Group boxes widened by half a pixel at their farthest corner from the eye."""
        return widen_boxes(self.g_lo, self.g_hi, eye, pixel)

    def wide(self, g_area: np.ndarray, o_area: np.ndarray) -> np.ndarray:
        """(m,) bool: the group's box covers more pixels than its parts' boxes together."""
        parts = np.bincount(self.leaf, weights=o_area, minlength=len(self.act))
        parts += np.bincount(self.child_parent, weights=g_area[self.child], minlength=len(self.act))
        return g_area > parts

    def open_free(self, frontier: np.ndarray, g_lo, g_hi, near, skip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Split the frontier into groups to query and, opening the others (``skip``, one
        part, reaching the near plane) down to groups worth a query, the query objects
        (positions) met on the way."""
        ask, objects = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        while len(frontier):
            free = skip[frontier] | (self.parts[frontier] < 2) | near(g_lo[frontier], g_hi[frontier])
            ask.append(frontier[~free])
            objects.append(self.own_objects(frontier[free]))
            frontier = self.children(frontier[free])
        return np.concatenate(ask), np.concatenate(objects)

    def children(self, groups: np.ndarray) -> np.ndarray:
        a = np.searchsorted(self.child_parent, groups, "left")
        return self.child[_ranges(a, np.searchsorted(self.child_parent, groups, "right"))]

    def own_objects(self, groups: np.ndarray) -> np.ndarray:
        """Positions (into the query list) of the query objects directly in ``groups``."""
        a = np.searchsorted(self.obj_leaf, groups, "left")
        return self.obj_order[_ranges(a, np.searchsorted(self.obj_leaf, groups, "right"))]

    def inherit(self, dead: np.ndarray) -> np.ndarray:
        """Per group, the samples of its nearest culled ancestor-or-self (−1: none)."""
        out = dead.copy()
        for level in self.by_depth[1:]:
            m = level[out[level] < 0]
            out[m] = out[self.parent[m]]
        return out


def _ranges(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(a[i], b[i])`` over i (int64)."""
    n = b - a
    total = int(n.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    starts = np.repeat(a - (np.cumsum(n) - n), n)
    return starts + np.arange(total)
