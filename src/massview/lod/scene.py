"""Scene skeleton culling and per-object LOD level choice (numpy only).

The skeleton of a scene store replaces every object's geometry by its bounding box, and its
group tree holds a box around every group of objects at every level of the scenegraph — the
scenegraph of the distributed massive-model paper (Mazumder et al., §3.2 "skeleton") with
geometry replaced by boxes. Culling walks that tree **level by level, vectorized**: each
depth's groups inherit their parent's state (outside / partly inside / inside) and only the
groups whose parent straddles a plane are tested; objects of a fully inside group are
accepted and objects of an outside group rejected without a test. The result equals testing
every object box against the frustum (:func:`boxes_in_frustum`), because a group box contains
the boxes below it.

Level choice (a pure function of the camera and the skeleton, so every rank agrees): the
world-space error ``level_error[i, l]`` of level ``l`` projects to
``err · K / d`` pixels with ``K = H / (2 tan(fovy/2))`` (pixels per world unit at distance 1,
from the *full* image, so all tiles agree) and ``d`` the distance from the eye to the nearest
point of the object's bounding sphere (clamped to the near plane). The chosen level is the
coarsest one whose projected error is at most ``tau`` pixels; level 0 (error 0) always passes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera
from .cull import boxes_in_frustum

__all__ = ["box_states", "SkeletonCuller", "lod_scale", "choose_levels", "resolve_levels", "build_group_tree", "GroupArrays"]

OUTSIDE, PARTIAL, INSIDE = 0, 1, 2


def box_states(lo: np.ndarray, hi: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(n,) int8 for (n, 3) float64 boxes against (6, 4) inward planes: 0 = entirely outside
    a plane, 2 = entirely inside all planes, 1 = otherwise (straddling)."""
    nrm = planes[:, :3]
    pos = nrm[None, :, :] >= 0
    far = np.where(pos, hi[:, None, :], lo[:, None, :])  # p-vertex: farthest along the normal
    near = np.where(pos, lo[:, None, :], hi[:, None, :])  # n-vertex: nearest
    dfar = np.einsum("bpk,pk->bp", far, nrm) + planes[:, 3]
    dnear = np.einsum("bpk,pk->bp", near, nrm) + planes[:, 3]
    out = np.full(len(lo), PARTIAL, np.int8)
    out[np.all(dnear >= 0, axis=1)] = INSIDE
    out[np.any(dfar < 0, axis=1)] = OUTSIDE
    return out


@dataclass(frozen=True)
class GroupArrays:
    """A group tree as arrays: parent (g,) int (-1 at roots), box_lo/box_hi (g, 3) float64,
    depth (g,) int (0 at roots). Shaped like the scene store's ``GroupTree``."""

    parent: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    depth: np.ndarray


class SkeletonCuller:
    """Hierarchical frustum culling of ``n`` objects (boxes ``obj_lo``/``obj_hi`` (n, 3),
    leaf group ``obj_group`` (n,)) through a group tree (anything with parent, box_lo,
    box_hi, depth arrays)."""

    def __init__(self, groups, obj_group: np.ndarray, obj_lo: np.ndarray, obj_hi: np.ndarray):
        self.parent = np.asarray(groups.parent, np.int64)
        self.g_lo = np.asarray(groups.box_lo, np.float64)
        self.g_hi = np.asarray(groups.box_hi, np.float64)
        depth = np.asarray(groups.depth, np.int64)
        self.by_depth = [np.flatnonzero(depth == d) for d in range(int(depth.max(initial=-1)) + 1)]
        self.obj_group = np.asarray(obj_group, np.int64)
        self.obj_lo = np.asarray(obj_lo, np.float64)
        self.obj_hi = np.asarray(obj_hi, np.float64)
        self.groups_tested = 0
        self.objects_tested = 0

    def group_states(self, planes: np.ndarray) -> np.ndarray:
        """(g,) int8 state of every group (OUTSIDE, PARTIAL, INSIDE)."""
        state = np.full(len(self.parent), PARTIAL, np.int8)
        tested = 0
        for ids in self.by_depth:
            p = self.parent[ids]
            ps = np.where(p >= 0, state[np.maximum(p, 0)], PARTIAL).astype(np.int8)
            t = ids[ps == PARTIAL]
            ps[ps == PARTIAL] = box_states(self.g_lo[t], self.g_hi[t], planes)
            state[ids] = ps
            tested += len(t)
        self.groups_tested = tested
        return state

    def visible(self, planes: np.ndarray) -> np.ndarray:
        """(n,) bool: the object's box is not entirely outside any plane."""
        if len(self.parent) == 0:
            self.objects_tested = len(self.obj_lo)
            return boxes_in_frustum(self.obj_lo, self.obj_hi, planes)
        st = self.group_states(planes)[self.obj_group]
        vis = st == INSIDE
        t = np.flatnonzero(st == PARTIAL)
        vis[t] = boxes_in_frustum(self.obj_lo[t], self.obj_hi[t], planes)
        self.objects_tested = len(t)
        return vis


def lod_scale(camera: Camera) -> float:
    """Pixels per world unit at distance 1 for the full image: H / (2 tan(fovy / 2))."""
    return camera.height / (2.0 * np.tan(np.radians(camera.fovy) / 2.0))


def choose_levels(camera: Camera, center: np.ndarray, radius: np.ndarray, levels: np.ndarray,
                  level_error: np.ndarray, tau: float) -> np.ndarray:
    """(n,) int64 level per object: the coarsest whose error, projected at the nearest point
    of the bounding sphere (``center`` (n, 3), ``radius`` (n,)), is at most ``tau`` pixels.
    ``levels`` (n,) counts each object's valid levels; ``level_error`` (n, Lmax) world units."""
    n = len(radius)
    if n == 0:
        return np.zeros(0, np.int64)
    diff = np.asarray(center, np.float64) - np.asarray(camera.position)
    d = np.maximum(np.sqrt(np.einsum("ij,ij->i", diff, diff)) - radius, camera.near)
    allowed = (d * (tau / lod_scale(camera))).astype(np.float32)  # world units
    err = np.asarray(level_error)
    lmax = err.shape[1]
    ok = (err <= allowed[:, None]) & (np.arange(lmax, dtype=np.int8)[None, :] < np.asarray(levels, np.int8)[:, None])
    return (ok * np.arange(lmax, dtype=np.int8)[None, :]).max(axis=1).astype(np.int64)


def resolve_levels(desired: np.ndarray, resident: np.ndarray) -> np.ndarray:
    """(n,) int64 level to draw now given (n, Lmax) bool residency: the desired level if
    resident, else the finest resident level coarser than it, else the coarsest resident
    finer one, else -1 (nothing to draw yet)."""
    n, lmax = resident.shape
    if n == 0:
        return np.zeros(0, np.int64)
    idx = np.arange(lmax)[None, :]
    coarser = resident & (idx >= desired[:, None])
    finer = resident & (idx < desired[:, None])
    first_coarser = np.argmax(coarser, axis=1)
    last_finer = lmax - 1 - np.argmax(finer[:, ::-1], axis=1)
    return np.where(coarser.any(axis=1), first_coarser, np.where(finer.any(axis=1), last_finer, -1)).astype(np.int64)


def build_group_tree(lo: np.ndarray, hi: np.ndarray, leaf_size: int = 64) -> tuple[GroupArrays, np.ndarray]:
    """A bounding-volume tree over (n, 3) object boxes by recursive median splits along the
    longest axis, built breadth-first with numpy. Returns the groups and each object's leaf
    group (n,) int32. Group boxes contain the boxes below them."""
    n = len(lo)
    c = (lo + hi) / 2
    parent, depth, members = [-1], [0], [np.arange(n)]
    leaf = np.zeros(n, np.int32)
    frontier = [0]
    while frontier:
        nxt = []
        for g in frontier:
            m = members[g]
            if len(m) <= leaf_size:
                leaf[m] = g
                continue
            ax = int(np.argmax(c[m].max(0) - c[m].min(0)))
            order = m[np.argsort(c[m, ax], kind="stable")]
            for half in (order[: len(m) // 2], order[len(m) // 2:]):
                parent.append(g)
                depth.append(depth[g] + 1)
                members.append(half)
                nxt.append(len(members) - 1)
        frontier = nxt
    g_lo = np.array([lo[m].min(0) if len(m) else np.zeros(3) for m in members])
    g_hi = np.array([hi[m].max(0) if len(m) else np.zeros(3) for m in members])
    return GroupArrays(np.array(parent, np.int32), g_lo, g_hi, np.array(depth, np.int16)), leaf
