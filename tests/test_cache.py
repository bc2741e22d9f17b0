"""BlockCache: never over budget, returns the stored bytes, loads asynchronously by priority."""

import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from massview.core.errors import CorruptBlockError
from massview.data.cache import BlockCache


class Store:
    """A fake block store with per-key sizes and an optional latency (like zarr's LatencyStore);
    a load of a key in ``held`` waits until the test opens ``gate`` (30 s at most), so tests
    about what happens while a load is in progress do not depend on timing."""

    def __init__(self, latency=0.0, held=()):
        self.latency = latency
        self.loads = []
        self.held, self.gate = set(held), threading.Event()

    def __call__(self, key):
        self.loads.append(key)
        if key in self.held:
            self.gate.wait(30)
        time.sleep(self.latency)
        if key == "bad":
            raise CorruptBlockError("block bad does not decode")
        rng = np.random.default_rng(hash(key) % 2**32)
        return rng.random(50 + (key % 7) * 30).astype(np.float32) if isinstance(key, int) else np.zeros(10)


@given(st.lists(st.tuples(st.integers(0, 40), st.floats(0, 10)), min_size=1, max_size=120), st.integers(1000, 4000))
@settings(max_examples=40, deadline=None)
def test_never_over_budget_and_returns_stored_bytes(ops, budget):
    store = Store()
    cache = BlockCache(store, budget, workers=2)
    seen_max = 0
    stop = threading.Event()

    def watch():
        nonlocal seen_max
        while not stop.is_set():
            seen_max = max(seen_max, cache.resident_bytes)

    w = threading.Thread(target=watch)
    w.start()
    try:
        for key, prio in ops:
            cache.request(key, prio)
            got = cache.get(key)
            if got is not None:
                assert np.array_equal(got, store(key))
        for key, _ in ops[-3:]:
            got = cache.get_blocking(key)
            assert np.array_equal(got, store(key))
    finally:
        stop.set()
        w.join()
        cache.close()
    assert seen_max <= budget and cache.resident_bytes <= budget


def _until(cond, limit=30.0):
    t0 = time.monotonic()
    while not cond():
        assert time.monotonic() - t0 < limit, "the cache's worker never started the load"  # a hang guard, not a speed test
        time.sleep(0.001)


def test_higher_priority_loads_first_and_stale_requests_drop():
    store = Store(held={100})
    cache = BlockCache(store, 10**6, workers=1, max_age=1)
    cache.request(100, 0.0)  # occupies the worker until the gate opens
    _until(lambda: store.loads == [100])
    for k, p in [(1, 1.0), (2, 5.0), (3, 3.0)]:
        cache.request(k, p)
    cache.begin_frame()
    cache.request(2, 5.0)
    cache.request(3, 3.0)  # 1 is not renewed
    cache.begin_frame()  # 1 was last asked for two frames ago: stale
    store.gate.set()
    while not cache.idle():
        time.sleep(0.005)
    cache.close()
    assert store.loads[0] == 100 and store.loads[1:3] == [2, 3]
    assert 1 not in store.loads and cache.stats()["dropped"] >= 1


def test_get_never_blocks_and_errors_surface():
    store = Store(held={5})
    cache = BlockCache(store, 10**6)
    cache.request(5)
    assert cache.get(5) is None  # the load is held until the gate opens: a get that waited for it would return the block
    store.gate.set()
    assert np.array_equal(cache.get_blocking(5), store(5))
    cache.request("bad")
    with pytest.raises(CorruptBlockError, match="block bad"):
        for _ in range(200):
            cache.get("bad")
            time.sleep(0.01)
    s = cache.stats()
    assert s["misses"] >= 1
    cache.close()
