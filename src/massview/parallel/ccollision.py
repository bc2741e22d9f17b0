"""Random replicated placement and the modified c-collision assignment (Süß et al. 2010, §6.2).

Object data are placed on the backends at random with a fixed number of replicas
(:func:`place_replicas`, 3 by default). Each frame the visualization rank assigns its new board
requests to backends with a modified c-collision protocol [Dietzfelbinger, Meyer auf der Heide
1993], in rounds made precise as follows:

1. Every unassigned request is offered to every backend holding a replica of its object.
2. A backend offered at most ``c`` requests accepts all of them; one offered more accepts none.
3. The accepted requests are settled in the order they were issued: a request accepted by
   several backends goes to the one with the fewest requests assigned so far in this frame,
   then the lowest rank. "Assigned" counts the assignments that persist from earlier frames
   (an assignment persists until its board arrives: ``outstanding``, the requests still pending
   on each backend) plus those made in this frame; without ``outstanding`` (the golden traces)
   only this frame's count.
4. ``c`` starts at 1; a round that assigns nothing raises ``c`` by one (until a round serves a
   request), and a round that assigns something resets ``c`` to 1.

Every request is served (each round with ``c`` ≥ the number of unassigned requests assigns at
least one), only by backends holding its object. As the paper says, the dynamic ``c`` gives up
the original protocol's contention bound; :class:`Assignment` reports the loads. The
assignment of a request persists until its board arrives (the caller keeps it and passes the
per-backend count back as ``outstanding``). Sending ties to the lowest rank instead would let
one backend take a whole burst of requests whose objects share holders; the fewest-assigned
rule spreads such a burst over the holders. Counting only this frame's assignments leaves a
skew *across* frames: a frame with one request always sends it to its lowest-rank holder
(measured on the forest with 4 backends: 26, 12, 2, 3 requests); counting the persisting
assignments sends it to the holder with the shortest queue instead — which changes nothing
when the boards arrive before the next request (measured: identical loads), so the system also
offers counting every assignment of the run (``--tie-rule run``).

Pure Python/numpy: no MPI here; the system sends the requests where this module says.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError

__all__ = ["place_replicas", "Assignment", "assign_requests"]


def place_replicas(n_objects: int, n_backends: int, replicas: int = 3, seed: int = 0) -> np.ndarray:
    """int32 (n_objects, min(replicas, n_backends)): distinct backend indices holding each
    object, drawn uniformly at random (seeded, so every rank computes the same placement)."""
    if n_backends < 1:
        raise ConfigError("Reliefboards need at least one backend rank (run with --ranks 2 or more)")
    if replicas < 1:
        raise ConfigError(f"--replicas must be at least 1, got {replicas}")
    r = min(replicas, n_backends)
    rng = np.random.default_rng(seed)
    keys = rng.random((n_objects, n_backends))
    return np.argsort(keys, axis=1)[:, :r].astype(np.int32)


@dataclass(frozen=True)
class Assignment:
    """backend: int32 (n_requests,) backend index per request, in issue order; loads: int64
    (n_backends,) requests assigned per backend; rounds: number of rounds; max_c: largest c used."""

    backend: np.ndarray
    loads: np.ndarray
    rounds: int
    max_c: int


def _round(unassigned: list[int], holders: np.ndarray, objects: np.ndarray, c: int, n_backends: int):
    """Which backends accept which requests in one round: a list of acceptor lists per request."""
    h = holders[objects[unassigned]].ravel()
    offered = np.bincount(h[h >= 0], minlength=n_backends)
    accepts = offered <= c
    return [[int(b) for b in holders[objects[q]] if b >= 0 and accepts[b]] for q in unassigned]


def assign_requests(objects, holders: np.ndarray, n_backends: int, outstanding=None) -> Assignment:
    """Assign requests for ``objects`` (int (n,), in issue order) to backends, where
    ``holders[o]`` lists the distinct backends with a replica of object ``o`` (rows padded
    with -1 where objects have fewer replicas). ``outstanding``: int (n_backends,) requests
    assigned earlier and not yet answered, counted as assigned in the tie rule (None: zeros; the
    system's ``--tie-rule run`` passes every earlier assignment of the run instead).
    ``Assignment.loads`` counts this frame's requests only."""
    objects = np.asarray(objects, np.int64)
    holders = np.asarray(holders)
    backend = np.full(len(objects), -1, np.int32)
    loads = np.zeros(n_backends, np.int64)
    held = np.zeros(n_backends, np.int64) if outstanding is None else np.asarray(outstanding, np.int64).copy()
    if held.shape != (n_backends,) or np.any(held < 0):
        raise ConfigError(f"outstanding must be {n_backends} non-negative counts, got {held.tolist()}")
    unassigned = list(range(len(objects)))
    c, rounds, max_c = 1, 0, 1
    while unassigned:
        rounds += 1
        max_c = max(max_c, c)
        acceptors = _round(unassigned, holders, objects, c, n_backends)
        left = []
        for q, acc in zip(unassigned, acceptors):
            if not acc:
                left.append(q)
                continue
            b = min(acc, key=lambda k: (held[k], k))
            backend[q] = b
            loads[b] += 1
            held[b] += 1
        c = c + 1 if len(left) == len(unassigned) else 1
        unassigned = left
    return Assignment(backend, loads, rounds, max_c)
