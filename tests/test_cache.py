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
    """A fake block store with per-key sizes and an optional latency (like zarr's LatencyStore)."""

    def __init__(self, latency=0.0):
        self.latency = latency
        self.loads = []

    def __call__(self, key):
        self.loads.append(key)
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


def test_higher_priority_loads_first_and_stale_requests_drop():
    store = Store(latency=0.02)
    cache = BlockCache(store, 10**6, workers=1, max_age=1)
    cache.request(100, 0.0)  # occupies the worker
    time.sleep(0.005)
    for k, p in [(1, 1.0), (2, 5.0), (3, 3.0)]:
        cache.request(k, p)
    cache.begin_frame()
    cache.request(2, 5.0)
    cache.request(3, 3.0)  # 1 is not renewed
    cache.begin_frame()  # 1 was last asked for two frames ago: stale
    while not cache.idle():
        time.sleep(0.005)
    cache.close()
    assert store.loads[0] == 100 and store.loads[1:3] == [2, 3]
    assert 1 not in store.loads and cache.stats()["dropped"] >= 1


def test_get_never_blocks_and_errors_surface():
    store = Store(latency=0.2)
    cache = BlockCache(store, 10**6)
    t0 = time.perf_counter()
    cache.request(5)
    assert cache.get(5) is None
    assert time.perf_counter() - t0 < 0.1  # not waiting for the 0.2 s load (loose bound on a non-blocking call)
    cache.request("bad")
    with pytest.raises(CorruptBlockError, match="block bad"):
        for _ in range(200):
            cache.get("bad")
            time.sleep(0.01)
    s = cache.stats()
    assert s["misses"] >= 1
    cache.close()
