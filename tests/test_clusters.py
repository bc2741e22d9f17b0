"""§4 clustering on hand-built scenes: merge order, refused merges past sl_c, infeasible objects, d_nz."""

import math

import numpy as np
import pytest

from massview.core.errors import ConfigError
from massview.lod.clusters import (FEASIBLE, TOO_FEW_TRIANGLES, TOO_LARGE, ClusterParams, agglomerate,
                                   cluster_scene, cluster_side_length, near_zone_range)


def cubes(xs, side=1.0):
    lo = np.array([[x, 0.0, 0.0] for x in xs])
    return lo, lo + side


def test_merges_smallest_joined_longest_side_first():
    lo, hi = cubes([0.0, 1.5, 5.0, 5.2, 20.0])
    _, merges, _ = agglomerate(lo, hi, np.ones(5, np.int64))
    assert [(a, b) for a, b, _ in merges] == [(2, 3), (0, 1), (0, 2), (0, 4)]
    assert [round(c, 6) for _, _, c in merges] == [1.2, 2.5, 6.2, 21.0]


def _brute_force(lo, hi):
    """All pairs every step (the O(n³) reference)."""
    lo, hi = lo.copy(), hi.copy()
    alive = list(range(len(lo)))
    out = []
    while len(alive) > 1:
        best = None
        for i in alive:
            for j in alive:
                if i < j:
                    c = (np.maximum(hi[i], hi[j]) - np.minimum(lo[i], lo[j])).max()
                    if best is None or c < best[2]:
                        best = (i, j, c)
        i, j, c = best
        lo[i], hi[i] = np.minimum(lo[i], lo[j]), np.maximum(hi[i], hi[j])
        alive.remove(j)
        out.append(c)
    return out


def test_all_candidates_reproduce_the_all_pairs_clustering_and_few_stay_monotone():
    rng = np.random.default_rng(3)
    lo = rng.uniform(0, 100, (40, 3))
    hi = lo + rng.uniform(0.5, 4, (40, 3))
    ref = _brute_force(lo, hi)
    _, merges, _ = agglomerate(lo, hi, np.ones(40, np.int64), k=39)
    assert np.allclose([c for _, _, c in merges], ref)
    _, merges8, _ = agglomerate(lo, hi, np.ones(40, np.int64), k=4)
    costs = np.array([c for _, _, c in merges8])
    assert len(costs) == 39 and np.all(np.diff(costs) >= -1e-12)  # a merged box never shrinks


def test_refused_merges_past_the_cap():
    lo, hi = cubes([10.0, 11.2, 12.5], side=0.5)
    labels, merges, _ = agglomerate(lo, hi, np.ones(3, np.int64), cap=2.0)
    assert [(a, b) for a, b, _ in merges] == [(0, 1)]  # {0,1}+2 would be 3.0 long
    assert labels.tolist() == [0, 0, 2]


def test_near_zone_range_is_the_diagonal_of_the_first_cluster_to_reach_tnz():
    lo, hi = cubes([0.0, 1.0, 10.0, 11.2])
    tris = np.array([600, 600, 50, 50])
    p = ClusterParams(t_nz=1000)
    assert near_zone_range(lo, hi, tris, p) == pytest.approx(math.sqrt(6))  # 2 x 1 x 1 box
    # a base cluster already past t_nz is the near zone by itself
    assert near_zone_range(lo, hi, np.array([600, 600, 2000, 50]), p) == pytest.approx(math.sqrt(3))
    # a scene below t_nz is all near zone: the scene diagonal
    assert near_zone_range(lo, hi, tris, ClusterParams(t_nz=10**6)) == pytest.approx(math.sqrt(12.2**2 + 2))


def test_cluster_scene_feasible_too_large_and_too_few():
    lo1, hi1 = cubes([0.0, 1.0])  # dense pair: reaches t_nz when joined, d_nz = sqrt(6)
    lo2, hi2 = cubes([10.0, 11.2, 12.5], side=0.5)  # light cubes
    lo = np.vstack([lo1, lo2, [[30.0, 0, 0]]])
    hi = np.vstack([hi1, hi2, [[33.0, 3, 3]]])  # a 3-unit box, longer than sl_c
    tris = np.array([600, 600, 50, 50, 50, 500])
    params = ClusterParams(t_nz=1000, p=64, r_y=128, fovy=90.0, min_triangles=100)
    cl = cluster_scene(lo, hi, tris, params)
    assert cl.d_nz == pytest.approx(math.sqrt(6))
    assert cl.sl_c == pytest.approx(cluster_side_length(cl.d_nz, params)) == pytest.approx(math.sqrt(6))
    groups = {tuple(np.nonzero(cl.labels == c)[0]) : int(cl.status[c]) for c in range(len(cl.status))}
    assert groups == {(0, 1): FEASIBLE, (2, 3): FEASIBLE, (4,): TOO_FEW_TRIANGLES, (5,): TOO_LARGE}
    assert cl.triangles[cl.labels[0]] == 1200
    assert np.all((cl.hi - cl.lo)[cl.feasible].max(axis=1) <= cl.sl_c)


def test_default_too_few_rule_is_the_largest_boards_triangles():
    assert ClusterParams().board_triangles == 2 * 128 * 128


def test_bad_input_names_the_parameter():
    with pytest.raises(ConfigError, match="tnz"):
        ClusterParams(t_nz=0)
    with pytest.raises(ConfigError, match="hi >= lo"):
        cluster_scene(np.ones((2, 3)), np.zeros((2, 3)), np.ones(2))


class _DenseAgglomerator:
    """The first implementation (kept as the reference): the k nearest by one distance pass over
    all active clusters, a global argmin over the (n, k) candidate table each merge — O(n) per
    merge with large constants. The KD-tree/heap version must merge in exactly the same order."""

    def __init__(self, lo, hi, k):
        self.lo, self.hi = lo.copy(), hi.copy()
        self.n = len(lo)
        self.k = max(1, min(k, self.n - 1))
        self.active = np.ones(self.n, bool)
        self.cand = np.zeros((self.n, self.k), np.int64)
        self.cost = np.full((self.n, self.k), np.inf)
        self._search(np.arange(self.n))

    def _price(self, rows):
        c = (np.maximum(self.hi[rows][:, None], self.hi[self.cand[rows]]) - np.minimum(self.lo[rows][:, None], self.lo[self.cand[rows]])).max(-1)
        c[self.cand[rows] == rows[:, None]] = np.inf
        self.cost[rows] = c

    def _search(self, rows):
        centre = (self.lo + self.hi) * 0.5
        others = np.nonzero(self.active)[0]
        d = ((centre[rows, None, :] - centre[None, others, :]) ** 2).sum(-1)
        d[rows[:, None] == others[None, :]] = np.inf
        kk = min(self.k, len(others) - 1)
        if kk < 1:
            self.cost[rows] = np.inf
            return
        near = np.argsort(d, axis=1, kind="stable")[:, :kk]
        self.cand[rows] = others[near[:, np.arange(self.k) % kk]]
        self._price(rows)

    def run(self):
        out = []
        while self.active.sum() > 1:
            flat = np.argmin(np.where(self.active[:, None], self.cost, np.inf))
            a, j = divmod(int(flat), self.k)
            cost = float(self.cost[a, j])
            if not np.isfinite(cost):
                break
            b = int(self.cand[a, j])
            a, b = min(a, b), max(a, b)
            self.lo[a], self.hi[a] = np.minimum(self.lo[a], self.lo[b]), np.maximum(self.hi[a], self.hi[b])
            self.active[b] = False
            self.cost[b] = np.inf
            self.cand[self.cand == b] = a
            touched = np.nonzero(np.any(self.cand == a, axis=1) & self.active)[0]
            self._price(touched)
            srt = np.sort(self.cand[touched], axis=1)
            distinct = 1 + (np.diff(srt, axis=1) != 0).sum(axis=1)
            stale = touched[(distinct < self.k) & (distinct < self.active.sum() - 1)]
            self._search(np.union1d(stale, [a]))
            out.append((a, b, cost))
        return out


def test_kdtree_heap_agglomeration_merges_in_the_dense_reference_order():
    rng = np.random.default_rng(11)
    n = 600  # clustered boxes of varied sizes, as a plant's parts; enough merges to rebuild the KD-tree snapshot
    centres = rng.uniform(0, 200, (30, 3))[rng.integers(30, size=n)] + rng.normal(0, 6, (n, 3))
    lo = centres - rng.uniform(0.1, 3, (n, 3))
    hi = centres + rng.uniform(0.1, 3, (n, 3))
    ref = _DenseAgglomerator(lo, hi, 8).run()
    _, merges, _ = agglomerate(lo, hi, np.ones(n, np.int64), k=8)
    assert len(merges) == len(ref) == n - 1
    assert [(a, b) for a, b, _ in merges] == [(a, b) for a, b, _ in ref]
    assert np.allclose([c for *_, c in merges], [c for *_, c in ref])
