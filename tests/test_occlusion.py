"""Occlusion culling of the massive-model client (§3.5) with real GL queries (Mesa llvmpipe):
conservative against an ID-buffer render, batched, n-frame marks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from massview.core.camera import Camera, Viewport
from massview.core.paths import load_path
from massview.data.generators import generate_objects
from massview.lod.cull import boxes_in_frustum
from massview.lod.visibility import VisibilityState, boxes_reach_near
from massview.render.meshes import MeshRenderer
from massview.render.queries import IdBuffer, OcclusionQuerier

W, H = 320, 240


def box_meshes(boxes):
    """Closed box meshes for [(lo, hi), ...]: positions, normals, colors, indices, offsets."""
    from massview.render.queries import _BOX_TRIANGLES, _CORNER_BITS

    pos, idx = [], []
    for j, (lo, hi) in enumerate(boxes):
        pos.append(np.where(_CORNER_BITS, np.asarray(hi, float), np.asarray(lo, float)))
        idx.append(_BOX_TRIANGLES + 8 * j)
    pos = np.concatenate(pos).astype(np.float32)
    normals = pos - pos.mean(axis=0)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors = np.full((len(pos), 4), 200, np.uint8)
    offs = np.arange(len(boxes) + 1, dtype=np.int64) * 36
    lo = np.array([b[0] for b in boxes], float)
    hi = np.array([b[1] for b in boxes], float)
    return pos, normals, colors, np.concatenate(idx).astype(np.uint32), offs, lo, hi


class Client:
    """A client's visibility pass over a scene of meshes, as the M1 system wires it."""

    def __init__(self, ctx, mesh, occluder, frames=4, batch=0):
        pos, nrm, col, idx, offs, self.lo, self.hi = mesh
        self.meshes = MeshRenderer(ctx, pos, nrm, col, idx, offs)
        self.ids = IdBuffer(ctx, pos, idx, offs)
        self.querier = OcclusionQuerier(ctx, batch=batch)
        self.state = VisibilityState(len(self.lo), frames)
        self.occluder = occluder

    def frame(self, f, cam, vp, items, threshold=0):
        near = boxes_reach_near(cam, self.lo[items], self.hi[items])
        plan = self.state.plan(f, items, self.occluder, near)
        res = self.querier.test(cam, vp, lambda mvp: self.meshes.draw(plan.depth_pass, mvp), self.lo[plan.query], self.hi[plan.query], threshold)
        return plan, res, self.state.finish(plan, res.passed)

    def release(self):
        for o in (self.meshes, self.ids, self.querier):
            o.release()


def wall_scene():
    """A wall (object 0, an occluder) in front of a 10×10 grid of boxes (1..100), and 20
    boxes (101..120) to its sides, seen from y = -40."""
    boxes = [((-8, -20.5, -3), (8, -20, 13))]
    for i in range(10):
        for k in range(10):
            x, z = -4.5 + i, 0.5 + k
            boxes.append(((x - 0.3, -0.3, z - 0.3), (x + 0.3, 0.3, z + 0.3)))
    for side in (-1, 1):
        for k in range(10):
            x, z = side * 22, 0.5 + k
            boxes.append(((x - 0.3, -0.3, z - 0.3), (x + 0.3, 0.3, z + 0.3)))
    cam = Camera.look_at((0, -40, 5), (0, 0, 5), fovy=60, near=0.5, far=200, width=W, height=H)
    occ = np.zeros(len(boxes), bool)
    occ[0] = True
    return box_meshes(boxes), occ, cam


def test_wall_culls_exactly_the_hundred_boxes_behind_it(ctx):
    mesh, occ, cam = wall_scene()
    c = Client(ctx, mesh, occ)
    try:
        items = np.nonzero(boxes_in_frustum(c.lo, c.hi, cam.frustum_planes()))[0]
        assert len(items) == 121
        plan, res, visible = c.frame(0, cam, cam.viewport, items)
        assert plan.query.tolist() == list(range(1, 121)) and res.issued == 120
        culled = set(plan.query[~res.passed].tolist())
        assert culled == set(range(1, 101))
        assert visible.tolist() == [0] + list(range(101, 121))
        truth = c.ids.visible(cam, cam.viewport, items)
        assert set(truth.tolist()) == set(visible.tolist())
        # a client whose viewport is the left half sees none of the right-hand boxes' pixels
        left = Viewport(0, 0, W // 2, H)
        plan, res, _ = c.frame(1, cam, left, np.array([0] + list(range(111, 121))))
        assert not res.passed.any() and (res.samples == 0).all()
    finally:
        c.release()


def test_box_seen_through_a_one_pixel_gap_is_kept(ctx):
    cam = Camera.look_at((0, 0, 0), (0, 1, 0), fovy=60, near=0.5, far=100, width=W, height=H)
    t = math.tan(math.radians(30))
    at = lambda px, d: ((2 * px / W) - 1) * d * t * W / H  # noqa: E731  world x of pixel x at depth d
    dw = 10.0
    wall_left = ((-50, dw, -50), (at(160.1, dw), dw + 0.5, 50))
    wall_right = ((at(160.9, dw), dw, -50), (50, dw + 0.5, 50))
    target = ((at(158, 20), 20, -1), (at(163, 20), 21, 1))
    mesh = box_meshes([wall_left, wall_right, target])
    c = Client(ctx, mesh, np.array([True, True, False]))
    try:
        truth = c.ids.visible(cam, cam.viewport, np.arange(3))
        assert truth.tolist() == [0, 1, 2]  # the ID buffer sees the box in column 160 only
        plan, res, visible = c.frame(0, cam, cam.viewport, np.arange(3))
        assert plan.query.tolist() == [2] and res.passed.tolist() == [True]
        assert 0 < res.samples[0] <= H  # one pixel column at most
        assert 2 in visible
        _, res, visible = c.frame(1, cam, cam.viewport, np.array([0, 1]))  # without the box: nothing to query
        assert res.issued == 0
        c.state = VisibilityState(3, 1)
        _, res, visible = c.frame(0, cam, cam.viewport, np.arange(3), threshold=int(res.samples.sum()) + H)
        assert 2 not in visible  # a threshold above the gap's pixel count culls it
    finally:
        c.release()


def test_queries_are_batched_and_batches_agree(ctx):
    mesh, occ, cam = wall_scene()
    items = np.arange(121)
    results = {}
    for batch in (0, 16, 1000):
        c = Client(ctx, mesh, occ, batch=batch)
        try:
            _, res, _ = c.frame(0, cam, cam.viewport, items)
            results[batch] = res
        finally:
            c.release()
    assert results[0].waits == 1 and results[1000].waits == 1
    assert results[16].waits == math.ceil(120 / 16)
    assert np.array_equal(results[0].samples, results[16].samples)


def test_box_containing_the_eye_is_visible_without_a_query(ctx):
    cam = Camera.look_at((0, 0, 0), (0, 1, 0), fovy=60, near=0.5, far=100, width=W, height=H)
    boxes = [((-1, -1, -1), (1, 1, 1)), ((-2, 5, -2), (2, 5.5, 2)), ((-0.2, 8, -0.2), (0.2, 9, 0.2))]
    mesh = box_meshes(boxes)
    c = Client(ctx, mesh, np.zeros(3, bool))
    try:
        near = boxes_reach_near(cam, c.lo, c.hi)
        assert near.tolist() == [True, False, False]
        plan, res, visible = c.frame(0, cam, cam.viewport, np.arange(3))
        assert plan.near.tolist() == [0] and plan.query.tolist() == [1, 2]
        assert res.issued == 2 and visible.tolist() == [0, 1, 2]
        c.occluder = np.array([False, True, False])  # box 1 hides box 2; box 0 is still not queried
        c.state = VisibilityState(3, 1)
        plan, res, visible = c.frame(1, cam, cam.viewport, np.arange(3))
        assert plan.near.tolist() == [0] and plan.query.tolist() == [2] and visible.tolist() == [0, 1]
    finally:
        c.release()


def test_marks_retest_after_n_frames():
    st = VisibilityState(4, frames=3)
    occ = np.array([True, False, False, False])
    items = np.arange(4)
    queried = []
    for f in range(8):
        plan = st.plan(f, items, occ)
        queried.append(plan.query.tolist())
        passed = np.isin(plan.query, [1, 2]) & ~((plan.query == 2) & (f >= 3))  # object 2 hides from frame 3 on
        vis = st.finish(plan, passed)
        if f == 0:
            assert vis.tolist() == [0, 1, 2]
        assert plan.depth_pass.tolist() == ([0] if f == 0 else sorted({0} | set(prev)))
        prev = vis.tolist()
    # 3 never passes: queried every frame; 1 passes at 0, 3, 6 (re-tested each 3rd frame); 2 passes at 0, then fails from 3 on
    assert queried == [[1, 2, 3], [3], [3], [1, 2, 3], [2, 3], [2, 3], [1, 2, 3], [2, 3]]
    with pytest.raises(ValueError):
        st.finish(st.plan(8, items, occ), np.zeros(5, bool))


def test_drawn_set_contains_every_visible_object_along_a_path(ctx):
    scene = generate_objects(400, 5)
    lo, hi = scene.box_lo, scene.box_hi
    occ = scene.triangles >= np.quantile(scene.triangles, 0.8)
    mesh = (scene.positions, scene.normals, scene.colors, scene.indices, scene.index_offset, lo, hi)
    c = Client(ctx, mesh, occ, frames=3)
    c2 = Client(ctx, mesh, occ, frames=3)
    try:
        cams = load_path("flyover", *scene.bounds).cameras(6, W, H)
        tiles = [Viewport(0, 0, 130, H), Viewport(130, 0, W - 130, H)]
        culled = 0
        for f, cam in enumerate(cams):
            items = np.nonzero(boxes_in_frustum(lo, hi, cam.frustum_planes()))[0]
            for client, vp in zip((c, c2), tiles):
                sub = np.nonzero(boxes_in_frustum(lo, hi, cam.frustum_planes(vp)))[0]
                plan, res, visible = client.frame(f, cam, vp, sub)
                truth = c.ids.visible(cam, vp, items)
                assert set(truth.tolist()) <= set(visible.tolist()), (f, vp, sorted(set(truth) - set(visible)))
                culled += int((~res.passed).sum())
        assert culled > 0
    finally:
        c.release()
        c2.release()


def test_coarse_occluders_can_hide_a_visible_object_exact_ones_cannot(ctx):
    """A simplified occluder that grew beyond the original's silhouette (here: a box twice as
    wide standing in for object 0's coarse level) hides object 2, which the exact occluder
    leaves visible: only exact occluder geometry is conservative (--occluder-lod exact)."""
    cam = Camera.look_at((0, -20, 0), (0, 0, 0), fovy=60, near=0.5, far=100, width=W, height=H)
    exact = ((-1, -10.5, -1), (1, -10, 1))
    coarse = ((-3, -10.5, -3), (3, -10, 3))
    behind = ((1.6, 0, -0.5), (2.6, 1, 0.5))  # seen beside the exact occluder, behind the coarse one
    mesh = box_meshes([exact, coarse, behind])
    c = Client(ctx, mesh, np.array([True, False, False]))
    try:
        truth = c.ids.visible(cam, cam.viewport, np.array([0, 2]))
        assert truth.tolist() == [0, 2]
        for occluder_mesh, kept in ((0, True), (1, False)):
            res = c.querier.test(cam, cam.viewport, lambda mvp: c.meshes.draw(np.array([occluder_mesh]), mvp), c.lo[[2]], c.hi[[2]])
            assert bool(res.passed[0]) is kept
    finally:
        c.release()
