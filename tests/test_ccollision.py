"""§6.2: random replicated placement and the modified c-collision assignment on golden traces."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from massview.core.errors import ConfigError
from massview.parallel.ccollision import assign_requests, place_replicas


def test_ring_of_pairs_needs_c_two_and_spreads_by_fewest_assigned():
    holders = np.array([[0, 1], [1, 2], [2, 3], [0, 3]])
    a = assign_requests([0, 1, 2, 3], holders, 4)
    # c=1: every backend is offered two requests and accepts none; c=2: all accept,
    # settled in issue order by fewest assigned so far, then lowest rank
    assert a.backend.tolist() == [0, 1, 2, 3]
    assert (a.rounds, a.max_c) == (2, 2)


def test_ties_go_to_the_fewest_assigned_then_the_lowest_rank():
    holders = np.array([[0, -1], [0, 1], [1, 2], [2, -1]])  # object 0 only on 0, object 3 only on 2
    # c=1: every backend is offered two; c=2: all accept and requests settle in issue order
    a = assign_requests([1, 0, 2, 3], holders, 3)
    assert a.backend.tolist() == [0, 0, 1, 2]  # object 1: tie at 0 assigned -> lowest rank
    assert a.loads.tolist() == [2, 1, 1]
    b = assign_requests([0, 1, 2, 3], holders, 3)
    assert b.backend.tolist() == [0, 1, 2, 2]  # object 1: backend 1 has fewer than backend 0


def test_backends_offered_at_most_c_accept_in_the_first_round():
    holders = np.array([[0, 1], [1, 2], [1, 3]])
    a = assign_requests([0, 1, 2], holders, 4)
    assert a.backend.tolist() == [0, 2, 3]  # backend 1 was offered 3 > c = 1 and took none
    assert a.rounds == 1


def test_c_resets_to_one_after_a_round_serves_a_request():
    # round 1 (c=1): backend 2 accepts the request for object 2; backend 0 (offered 2) takes none.
    # round 2 (c=1): backend 0 still offered 2 -> nothing; round 3 (c=2): both go to backend 0.
    holders = np.array([[0], [0], [2]])
    a = assign_requests([0, 1, 2], holders, 3)
    assert a.backend.tolist() == [0, 0, 2]
    assert (a.rounds, a.max_c) == (3, 2)


def test_a_burst_on_shared_holders_is_spread_over_them():
    holders = np.tile([5, 9, 17], (128, 1))  # 128 objects on the same three of 32 backends
    a = assign_requests(np.arange(128), holders, 32)
    assert sorted(a.loads[[5, 9, 17]].tolist()) == [42, 43, 43] and a.loads.sum() == 128


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 12), st.integers(1, 4), st.integers(0, 60), st.integers(0, 10**6))
def test_every_request_is_served_by_a_replica_holder(nb, reps, nreq, seed):
    holders = place_replicas(40, nb, reps, seed)
    objects = np.random.default_rng(seed).choice(40, size=min(nreq, 40), replace=False)
    a = assign_requests(objects, holders, nb)
    assert np.all(a.backend >= 0)
    assert all(b in holders[o] for o, b in zip(objects, a.backend))
    assert a.loads.sum() == len(objects) and np.array_equal(np.bincount(a.backend, minlength=nb), a.loads)


def test_placement_is_random_distinct_and_reproducible():
    h = place_replicas(1000, 8, 3, seed=1)
    assert h.shape == (1000, 3) and np.all(np.sort(h, 1)[:, 1:] != np.sort(h, 1)[:, :-1])
    assert np.array_equal(h, place_replicas(1000, 8, 3, seed=1))
    counts = np.bincount(h.ravel(), minlength=8)
    assert counts.min() > 300 and counts.max() < 450  # 375 expected per backend
    assert place_replicas(10, 2, 3).shape == (10, 2)
    with pytest.raises(ConfigError, match="backend"):
        place_replicas(10, 0)


def test_persisting_assignments_count_in_the_tie_rule():
    holders = np.array([[0, 1, 2]] * 4)
    # one request per frame: alone, each would go to the lowest rank; counting the requests
    # still pending on each backend (an assignment persists until its board arrives) spreads them
    assert assign_requests([0], holders, 3).backend.tolist() == [0]
    pending = np.zeros(3, np.int64)
    for o in range(4):
        a = assign_requests([o], holders, 3, outstanding=pending)
        pending += a.loads
    assert pending.tolist() == [2, 1, 1] and a.loads.sum() == 1
    b = assign_requests([0, 1], holders, 3, outstanding=[0, 0, 0])
    assert b.backend.tolist() == assign_requests([0, 1], holders, 3).backend.tolist() == [0, 1]
    with pytest.raises(ConfigError, match="outstanding"):
        assign_requests([0], holders, 3, outstanding=[1, 2])
