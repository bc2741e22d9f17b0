"""Algorithm 1 (load-balanced frustum division, Revanth & Narayanan 2012 §3.4) against a
literal transcription of the paper, brute force, and load balance on random object sets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from massview.core.camera import Camera, Viewport
from massview.lod.split import choose_split, divide_frustum, sphere_rects, split_cost
from massview.parallel.decompose import parse_decomposition, sort_first_tiles

from conftest import SMALL_SCENE, SMALL_SIZE, run_cli, summary

# hand-built 1-D object sets: (left, right, weight); integer weights keep every sum exact
HAND_SETS = {
    "distinct": [(0, 10, 5), (5, 20, 3), (15, 30, 8), (25, 40, 2), (35, 50, 6)],
    "exact_tie": [(0, 1, 1), (2, 3, 1)],  # lower_bound comes out above upper_bound
    "one_heavy": [(0, 4, 1), (10, 90, 50), (20, 24, 1), (60, 64, 1), (95, 99, 1)],
    "nested": [(0, 100, 7), (10, 20, 3), (30, 40, 3), (50, 60, 3), (70, 80, 3)],
    "same_point": [(50, 50, 2), (50, 50, 2), (50, 50, 2)],
    "zero_width_mix": [(0, 0, 4), (10, 10, 4), (10, 30, 2), (30, 30, 1), (31, 45, 6)],
}


def _positions(objs):
    """Each object's (left index, right index) among the sorted 2n bounds (coordinate, then
    left before right, then object id) — computed with Python's sort, independently."""
    pts = sorted([(a, 0, j) for j, (a, _, _) in enumerate(objs)] + [(b, 1, j) for j, (_, b, _) in enumerate(objs)])
    li, ri = {}, {}
    for i, (_, side, j) in enumerate(pts):
        (li if side == 0 else ri)[j] = i
    return pts, li, ri


def _brute(objs, nd):
    """lower_bound, upper_bound and the argmin of the generalised cost, by direct sums."""
    pts, li, ri = _positions(objs)
    n, k = len(pts), nd // 2
    W = sum(w for _, _, w in objs)
    hl, hr = W * k / nd, W * (nd - k) / nd
    left = [sum(w for j, (_, _, w) in enumerate(objs) if li[j] < i) for i in range(n + 1)]
    right = [sum(w for j, (_, _, w) in enumerate(objs) if ri[j] > i) for i in range(-1, n)]  # right[i+1] = Rw_i
    lower = min(i for i in range(n) if left[i + 1] > hl)
    upper = max(i for i in range(n) if right[i] > hr)
    lo, hi = min(lower, upper), max(lower, upper)
    costs = [abs(left[i] - hl) + abs(right[i + 1] - hr) + nd / 2 * abs(left[i] / k - right[i + 1] / (nd - k)) for i in range(lo, hi + 1)]
    return lower, upper, lo + costs.index(min(costs))


@pytest.mark.parametrize("name", sorted(HAND_SETS))
@pytest.mark.parametrize("nd", [2, 3, 4, 5, 7])
def test_chosen_index_is_the_brute_force_argmin(name, nd):
    objs = HAND_SETS[name]
    a, b, w = (np.array(c, np.float64) for c in zip(*objs))
    lower, upper, divide, P, Lw, Rw = choose_split(a, b, w, nd)
    assert (lower, upper, divide) == _brute(objs, nd)
    assert np.all(np.diff(P) >= 0)


def test_exact_ties_put_lower_bound_above_upper_bound_and_search_between():
    a, b, w = np.array([0.0, 2.0]), np.array([1.0, 3.0]), np.array([1.0, 1.0])
    lower, upper, divide, P, _, _ = choose_split(a, b, w, 2)
    assert (lower, upper) == (2, 1)
    assert divide == 1 and P[divide] == 1.0  # cost 0 at both 1 and 2: ties go to the lower index
    subs = divide_frustum(np.array([[0, 0, 1, 1], [2, 0, 3, 1]], float), w, Viewport(0, 0, 4, 1), 2)
    assert [s.viewport for s in subs] == [Viewport(0, 0, 1, 1), Viewport(1, 0, 3, 1)]
    assert [s.items.tolist() for s in subs] == [[0], [1]]


def test_cost_is_the_papers_for_even_counts():
    rng = np.random.default_rng(1)
    l, r = rng.uniform(0, 100, 50), rng.uniform(0, 100, 50)
    for nd in (2, 4, 6, 8):
        h = 100 / 2
        assert np.allclose(split_cost(l, r, 100.0, nd), np.abs(l - h) + np.abs(r - h) + np.abs(l - r))


# -- a literal transcription of the paper's Algorithm 1 (powers of two) --------------------
def _paper_divide(objs, rect, nd, direction, out):
    """objs: list of (id, x0, y0, x1, y1, weight); rect: (x0, y0, x1, y1) ints."""
    if nd == 1:
        out.append((rect, sorted(o[0] for o in objs)))
        return
    lo, hi = (rect[0], rect[2]) if direction == 0 else (rect[1], rect[3])
    clamp = lambda v: min(max(v, lo), hi)  # noqa: E731
    P = []
    for o in objs:
        P.append((clamp(o[1 + direction]), 0, o[0], o[5]))
        P.append((clamp(o[3 + direction]), 1, o[0], o[5]))
    P.sort()
    n = len(P)
    total = sum(p[3] for p in P if p[1] == 0)
    Lw = [sum(p[3] for p in P[:i] if p[1] == 0) for i in range(n + 1)]
    Rw = [sum(p[3] for p in P[i + 1:] if p[1] == 1) for i in range(n)]
    h = total / 2
    if n == 0 or total == 0:
        edge = math.floor(lo + (hi - lo) / 2 + 0.5)
    else:
        lower = min(i for i in range(n) if Lw[i + 1] > h)
        upper = max(i for i in range(n) if (Rw[i - 1] if i > 0 else total) > h)
        best = None
        for i in range(min(lower, upper), max(lower, upper) + 1):
            c = abs(Lw[i] - h) + abs(Rw[i] - h) + abs(Lw[i] - Rw[i])  # OptimalWeight
            if best is None or c < best[0]:
                best = (c, i)
        edge = clamp(math.floor(P[best[1]][0] + 0.5))
    a_of = {o[0]: clamp(o[1 + direction]) for o in objs}
    b_of = {o[0]: clamp(o[3 + direction]) for o in objs}
    left = [o for o in objs if a_of[o[0]] < edge or b_of[o[0]] <= edge]
    right = [o for o in objs if b_of[o[0]] > edge or a_of[o[0]] >= edge]
    ra, rb = list(rect), list(rect)
    ra[2 + direction], rb[direction] = edge, edge
    _paper_divide(left, tuple(ra), nd // 2, 1 - direction, out)
    _paper_divide(right, tuple(rb), nd // 2, 1 - direction, out)


def _random_rects(rng, n, width, height, size=(1.0, 8.0), clustered=False):
    if clustered:
        centers = rng.uniform([0, 0], [width, height], (5, 2))
        xy = centers[rng.integers(0, 5, n)] + rng.normal(0, 0.12 * width, (n, 2))
    else:
        xy = rng.uniform([0, 0], [width, height], (n, 2))
    half = rng.uniform(*size, (n, 2)) / 2
    rects = np.concatenate([xy - half, xy + half], axis=1)
    return rects, rng.integers(50, 2000, n).astype(np.float64)


@pytest.mark.parametrize("nd", [2, 4])
@pytest.mark.parametrize("seed", range(4))
def test_powers_of_two_equal_the_papers_algorithm(nd, seed):
    rng = np.random.default_rng(seed)
    rects, w = _random_rects(rng, 60, 160, 120, size=(1, 30), clustered=seed % 2 == 1)
    rects = np.round(rects * 4) / 4  # quarter pixels: exact ties happen
    subs = divide_frustum(rects, w, Viewport(0, 0, 160, 120), nd)
    ref = []
    _paper_divide([(j, *rects[j], w[j]) for j in range(len(w))], (0, 0, 160, 120), nd, 0, ref)
    got = [((s.viewport.x, s.viewport.y, s.viewport.x + s.viewport.w, s.viewport.y + s.viewport.h), s.items.tolist()) for s in subs]
    assert got == ref


@pytest.mark.parametrize("seed", range(4))
def test_six_clients_split_first_as_the_paper(seed):
    rng = np.random.default_rng(10 + seed)
    rects, w = _random_rects(rng, 80, 200, 100, size=(1, 20))
    trace = []
    divide_frustum(rects, w, Viewport(0, 0, 200, 100), 6, trace=trace)
    ref = []
    _paper_divide([(j, *rects[j], w[j]) for j in range(len(w))], (0, 0, 200, 100), 2, 0, ref)
    assert trace[0].edge == ref[0][0][2]


def _expected_axes(nd, axis=0):
    if nd == 1:
        return []
    return [axis] + _expected_axes(nd // 2, 1 - axis) + _expected_axes(nd - nd // 2, 1 - axis)


@pytest.mark.parametrize("nd", range(1, 8))
def test_partition_cover_alternation(nd):
    rng = np.random.default_rng(nd)
    W, H = 320, 240
    rects, w = _random_rects(rng, 500, W, H, size=(1, 60), clustered=True)
    trace = []
    subs = divide_frustum(rects, w, Viewport(0, 0, W, H), nd, trace=trace)
    assert len(subs) == nd
    assert [t.axis for t in trace] == _expected_axes(nd)  # directions alternate with depth
    owner = np.full((H, W), -1)
    for i, s in enumerate(subs):  # the tiles partition the image
        assert (owner[s.viewport.slices()] == -1).all()
        owner[s.viewport.slices()] = i
    assert (owner >= 0).all()
    for j in range(len(w)):  # every object is on >= 1 side, and in every tile with a pixel centre it may cover
        holders = {i for i, s in enumerate(subs) if j in s.items}
        assert holders
        x0, y0, x1, y1 = rects[j]
        for i, s in enumerate(subs):
            v = s.viewport
            mx = (max(math.ceil(x0 - 0.5), v.x), min(math.floor(x1 - 0.5), v.x + v.w - 1))
            my = (max(math.ceil(y0 - 0.5), v.y), min(math.floor(y1 - 0.5), v.y + v.h - 1))
            if mx[0] <= mx[1] and my[0] <= my[1]:
                assert i in holders, (j, i, rects[j], v)


@pytest.mark.parametrize("nd", range(1, 8))
def test_most_loaded_share_on_many_small_objects(nd):
    ratios = []
    for seed in range(15):
        rng = np.random.default_rng(100 * nd + seed)
        rects, w = _random_rects(rng, 3000, 1280, 1024, size=(2, 12), clustered=seed % 3 == 0)
        subs = divide_frustum(rects, w, Viewport(0, 0, 1280, 1024), nd)
        ratios.append(max(s.weight for s in subs) / (w.sum() / nd))
    assert np.median(ratios) <= 1.1, ratios


def test_sphere_rects_bound_the_projected_surface():
    cam = Camera.look_at((0, -20, 3), (1, 0, 1), width=200, height=150, near=0.1, far=100)
    rng = np.random.default_rng(3)
    centers = rng.uniform([-6, -4, -3], [6, 6, 5], (40, 3))
    radii = rng.uniform(0.2, 2.0, 40)
    rects = sphere_rects(cam, centers, radii)
    for c, r, rect in zip(centers, radii, rects):
        d = rng.normal(size=(4000, 3))
        surf = c + r * d / np.linalg.norm(d, axis=1, keepdims=True)
        px, depth = cam.project(surf)
        px = px[depth > 0]
        px = px[(px[:, 0] >= 0) & (px[:, 0] <= 200) & (px[:, 1] >= 0) & (px[:, 1] <= 150)]
        if len(px):
            assert (px[:, 0] >= rect[0] - 1e-6).all() and (px[:, 0] <= rect[2] + 1e-6).all()
            assert (px[:, 1] >= rect[1] - 1e-6).all() and (px[:, 1] <= rect[3] + 1e-6).all()
            # tight: the sampled surface reaches within a pixel of the bound on each free side
            for k, lim in ((0, 0), (1, 0), (2, 200), (3, 150)):
                if rect[k] not in (0, lim):
                    assert np.min(np.abs(px[:, k % 2] - rect[k])) < 1.0


def test_balanced_is_a_sort_first_layout():
    assert parse_decomposition("sort-first:balanced") == ("sort-first", "balanced")
    rng = np.random.default_rng(0)
    rects, w = _random_rects(rng, 200, 320, 240)
    for n in (1, 3, 5):
        tiles = sort_first_tiles("balanced", n, 320, 240, rects=rects, weights=w)
        assert tiles == [s.viewport for s in divide_frustum(rects, w, Viewport(0, 0, 320, 240), n)]
        assert sum(t.area for t in tiles) == 320 * 240
    assert sort_first_tiles("kd", 3, 320, 240, rects=rects, weights=w, alternate=True) == sort_first_tiles("balanced", 3, 320, 240, rects=rects, weights=w)


@pytest.mark.mpi
@pytest.mark.parametrize("ranks", [3, 4])
def test_balanced_layout_renders_bit_exact(tmp_path, ranks):
    run_cli("render", SMALL_SCENE, "--ranks", ranks, "--decomposition", "sort-first:balanced", "--frames", 2,
            "--size", SMALL_SIZE, "--out", tmp_path, "--reference", "-q")
    s = summary(tmp_path)
    assert s["max_abs_diff"] == 0 and s["diff_fraction"] == 0.0
