"""A byte-budget LRU block cache with asynchronous, prioritized loading.

Wraps any ``load(key) -> numpy array`` (a store's ``get_block``). The render thread never
blocks on it:

* ``request(key, priority)`` queues a load (higher priority first, e.g. screen-space
  importance) or renews a queued one; it returns at once.
* ``get(key)`` returns the resident array (and marks it recently used) or None.
* ``discard(key)`` drops a resident array whose data the caller now keeps elsewhere;
* ``begin_frame()`` advances the frame clock; queued requests not renewed for ``max_age``
  frames are dropped, so a camera that moved on does not keep stale loads in the queue.

Worker threads load outside the lock and insert with LRU eviction; resident bytes never
exceed ``budget_bytes``. A load that fails is remembered and its error re-raised by ``get``
(so a corrupt block surfaces on the render thread, with the store's message). Counters: hits,
misses, loads, bytes loaded, evictions, dropped requests, load latency.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections import OrderedDict
from typing import Callable, Hashable

import numpy as np

from ..core.errors import ConfigError

__all__ = ["BlockCache"]


class BlockCache:
    def __init__(self, load: Callable[[Hashable], np.ndarray], budget_bytes: int, workers: int = 2, max_age: int = 2):
        if budget_bytes <= 0:
            raise ConfigError(f"cache budget must be positive, got {budget_bytes} bytes")
        self._load = load
        self.budget = int(budget_bytes)
        self.max_age = int(max_age)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._resident: OrderedDict[Hashable, np.ndarray] = OrderedDict()
        self._bytes = 0
        self.peak_bytes = 0  # most bytes ever resident (≤ budget)
        self._heap: list = []
        self._pending: dict[Hashable, tuple[float, int]] = {}  # key -> (priority, frame renewed)
        self._loading: set = set()
        self._failed: dict[Hashable, BaseException] = {}
        self._seq = itertools.count()
        self._frame = 0
        self._closed = False
        self.counters = {"hits": 0, "misses": 0, "loads": 0, "bytes_loaded": 0, "evictions": 0, "dropped": 0, "discarded": 0,
                         "load_seconds": 0.0}
        self._threads = [threading.Thread(target=self._worker, name=f"massview-load-{i}", daemon=True) for i in range(max(1, workers))]
        for t in self._threads:
            t.start()

    # -- render-thread API -------------------------------------------------------------
    def get(self, key):
        with self._lock:
            arr = self._resident.get(key)
            if arr is not None:
                self._resident.move_to_end(key)
                self.counters["hits"] += 1
                return arr
            if key in self._failed:
                raise self._failed[key]
            self.counters["misses"] += 1
            return None

    def contains(self, key) -> bool:
        with self._lock:
            return key in self._resident

    def request(self, key, priority: float = 0.0) -> None:
        with self._lock:
            if key in self._resident or key in self._loading or key in self._failed:
                return
            old = self._pending.get(key)
            newp = max(priority, old[0]) if old and old[1] == self._frame else priority
            self._pending[key] = (newp, self._frame)
            if old is None or newp != old[0]:  # the heap entry carrying the current priority
                heapq.heappush(self._heap, (-newp, next(self._seq), key))
                self._wake.notify()

    def begin_frame(self) -> None:
        with self._lock:
            self._frame += 1
            stale = [k for k, (_, f) in self._pending.items() if self._frame - f > self.max_age]
            for k in stale:
                del self._pending[k]
            self.counters["dropped"] += len(stale)

    def discard(self, key) -> bool:
        """Drop ``key``'s resident array (its bytes leave the budget at once); True if it was
        resident. For a caller that moved the data into a cache of its own (the terrain GL pool)
        and would otherwise hold every block twice."""
        with self._lock:
            arr = self._resident.pop(key, None)
            if arr is None:
                return False
            self._bytes -= arr.nbytes
            self.counters["discarded"] += 1
            return True

    def get_blocking(self, key, timeout: float = 60.0):
        """Request and wait (tools and tests; the render loop never calls this)."""
        t0 = time.monotonic()
        while True:
            self.request(key, float("inf"))  # again each time: it may be evicted in between
            arr = self.get(key)
            if arr is not None:
                return arr
            if time.monotonic() - t0 > timeout:
                raise TimeoutError(f"block {key} did not load within {timeout} s")
            time.sleep(0.001)

    @property
    def resident_bytes(self) -> int:
        with self._lock:
            return self._bytes

    def idle(self) -> bool:
        with self._lock:
            return not self._pending and not self._loading

    def stats(self) -> dict:
        with self._lock:
            c = dict(self.counters)
            c["resident_bytes"] = self._bytes
            c["peak_bytes"] = self.peak_bytes
            c["resident"] = len(self._resident)
            c["queued"] = len(self._pending)
        c["mean_load_ms"] = 1e3 * c["load_seconds"] / c["loads"] if c["loads"] else 0.0
        return c

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._wake.notify_all()
        for t in self._threads:
            t.join(timeout=5)

    # -- workers -----------------------------------------------------------------------
    def _next(self):
        while True:
            if self._closed:
                return None
            while self._heap:
                negp, _, key = heapq.heappop(self._heap)
                entry = self._pending.get(key)
                if entry is None or entry[0] != -negp:  # dropped, or superseded by a renewal
                    continue
                del self._pending[key]
                self._loading.add(key)
                return key
            self._wake.wait()

    def _worker(self) -> None:
        while True:
            with self._lock:
                key = self._next()
            if key is None:
                return
            t0 = time.perf_counter()
            try:
                arr = self._load(key)
                err = None
            except BaseException as e:  # noqa: BLE001 - surfaced to the render thread by get()
                arr, err = None, e
            dt = time.perf_counter() - t0
            with self._lock:
                self._loading.discard(key)
                if err is not None:
                    self._failed[key] = err
                    continue
                self.counters["loads"] += 1
                self.counters["bytes_loaded"] += arr.nbytes
                self.counters["load_seconds"] += dt
                self._insert(key, arr)

    def _insert(self, key, arr: np.ndarray) -> None:
        if arr.nbytes > self.budget:
            self._failed[key] = ConfigError(f"block {key} is {arr.nbytes} bytes, more than the whole cache budget ({self.budget}); raise the budget")
            return
        while self._bytes + arr.nbytes > self.budget and self._resident:
            _, old = self._resident.popitem(last=False)
            self._bytes -= old.nbytes
            self.counters["evictions"] += 1
        self._resident[key] = arr
        self._bytes += arr.nbytes
        self.peak_bytes = max(self.peak_bytes, self._bytes)
