"""The ingest's thread pool: how many workers, and ordered, bounded task submission.

Ingest work is numpy (which releases the GIL on array operations), the compiled kernels of
:mod:`kernels` (``nogil``) and blosc (de)compression inside zarr (its own threads), so threads
of one process use every core without copying data between processes. Every result is
combined by exact operations (max, min, disjoint writes), so the output does not depend on the
number of workers or on the order tasks finish in (tests/test_ingest_parallel.py).
"""

from __future__ import annotations

import os
import threading
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from typing import Callable, Iterable

import numpy as np

from ...core.errors import ConfigError

__all__ = ["resolve_workers", "run_ordered", "run_ready", "BufferPool", "return_freed_memory"]


def resolve_workers(workers: int | None) -> int:
    """``None`` or 0 → the CPUs this process may run on; otherwise at least 1."""
    if workers is None or workers == 0:
        try:
            return max(len(os.sched_getaffinity(0)), 1)
        except AttributeError:  # pragma: no cover - not Linux
            return os.cpu_count() or 1
    if workers < 0:
        raise ConfigError(f"--workers must be 0 (all cores) or a positive count, got {workers}")
    return int(workers)


def run_ordered(workers: int, tasks: Iterable[Callable[[], object]], done: Callable[[object], None] | None = None,
                depth: int = 2) -> None:
    """Run ``tasks`` (zero-argument callables, produced lazily) on ``workers`` threads with at
    most ``depth × workers`` of them unfinished (queued or running) at once, and hand each
    result to ``done`` in submission order (on the calling thread). A task that finished
    before an older one waits for it with only its result held, and the next task is submitted
    at once: a slow task never leaves a worker idle (waiting for the oldest task, as this did
    before issue 20's fifth round, left one of two workers idle while it ran), and no more
    inputs are alive than before. One worker runs everything inline, in order. If producing a
    task or a task fails, the tasks already submitted are still finished and handed to
    ``done`` in order up to the first failure (so work that reached the disk is recorded as
    done, for a resumed run), then the error is raised."""
    sink = done or (lambda r: None)
    if workers <= 1:
        for t in tasks:
            sink(t())
        return
    limit = depth * workers
    pending: deque[Future] = deque()
    failed = []

    def take() -> None:  # the oldest result to ``done``; a failed task's error is raised
        f = pending.popleft()
        if f.exception() is not None:
            failed.append(f)
        sink(f.result())

    with ThreadPoolExecutor(workers, thread_name_prefix="ingest") as ex:
        try:
            for t in tasks:
                pending.append(ex.submit(t))
                while True:
                    while pending and pending[0].done():
                        take()
                    busy = [f for f in pending if not f.done()]
                    if len(busy) < limit and len(pending) < 4 * limit:  # (finished results wait, but not without bound)
                        break
                    wait(busy, return_when=FIRST_COMPLETED)
            while pending:
                take()
        except BaseException:
            while pending and not failed:  # (producing a task failed, or ``done``: finish what was submitted)
                try:
                    res = pending.popleft().result()
                except BaseException:  # noqa: BLE001 - the first error is the one raised
                    break
                sink(res)
            for f in pending:
                f.cancel()
            raise


def run_ready(workers: int, first: Iterable[Callable[[], object]], then: Callable[[object], Iterable[Callable[[], object]]],
              done: Callable[[object], None] | None = None, depth: int = 1) -> None:
    """Run the tasks of ``first`` (produced lazily, in order) and the tasks that finished ones
    make ready on ``workers`` threads, no task ever waiting for another: ``then(result)``,
    called on this thread as each task finishes, returns the tasks whose inputs are now all
    there; they are submitted before the next task of ``first``. At most ``depth × workers``
    tasks are unfinished at once; ``done(result)`` sees every result, in the order they finish.
    One worker runs everything inline (each task's ready tasks before the next of ``first``).
    If producing a task, a task, ``then`` or ``done`` fails, nothing more is submitted, the
    running tasks are finished (their results still handed on) and the first error is raised."""
    sink = done or (lambda r: None)
    ready: deque = deque()
    if workers <= 1:
        for t in first:
            ready.append(t)
            while ready:
                res = ready.popleft()()
                sink(res)
                ready.extend(then(res))
        return
    source, running, errors = iter(first), set(), []
    limit = depth * workers
    with ThreadPoolExecutor(workers, thread_name_prefix="ingest") as ex:
        while True:
            while not errors and len(running) < limit:
                try:
                    t = ready.popleft() if ready else next(source, None)
                except BaseException as e:  # noqa: BLE001 - producing a task failed: finish the running ones
                    errors.append(e)
                    break
                if t is None:
                    break
                running.add(ex.submit(t))
            if not running:
                break
            finished, running = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                try:
                    res = f.result()
                    sink(res)
                    if not errors:
                        ready.extend(then(res))
                except BaseException as e:  # noqa: BLE001 - the first error is the one raised
                    errors.append(e)
    if errors:
        raise errors[0]


class BufferPool:
    """Large arrays handed back for reuse instead of freed (thread-safe). A new large array is
    a fresh mapping (:func:`return_freed_memory`) whose every page faults in, zero-filled, when
    first written; a pass that allocates a 50 MB row per task spends seconds of system time on
    that. ``take`` returns a buffer of that shape and dtype given back earlier, or a new one
    (contents undefined, like ``np.empty``). At most ``keep`` bytes of buffers wait in the pool
    (one given back beyond that is freed), so the pool adds at most that to the peak memory."""

    def __init__(self, keep: int):
        self._free: dict = {}
        self._keep, self._bytes = keep, 0
        self._lock = threading.Lock()

    def take(self, shape: tuple, dtype) -> np.ndarray:
        key = (tuple(shape), np.dtype(dtype).str)
        with self._lock:
            free = self._free.get(key)
            if free:
                self._bytes -= free[-1].nbytes
                return free.pop()
        return np.empty(shape, dtype)

    def give(self, a: np.ndarray) -> None:
        with self._lock:
            if self._bytes + a.nbytes <= self._keep:
                self._free.setdefault((a.shape, a.dtype.str), []).append(a)
                self._bytes += a.nbytes


def return_freed_memory(mmap_min: int = 1 << 20) -> bool:
    """Serve buffers of ``mmap_min`` bytes and more (block rows, strips: 1–50 MB) from their
    own mappings, unmapped when freed. The renderer's start-up setting keeps freed blocks up to
    32 MiB in glibc's heap for reuse (``parallel.runtime.reuse_freed_memory``); with several
    ingest threads, each with its own heap arena, that kept ~1 GiB resident at 16385². The
    ingest commands call this once at start; a no-op (False) where the C library is not glibc."""
    import ctypes
    import ctypes.util

    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h>
    return bool(mallopt(m_mmap_threshold, mmap_min)) and bool(mallopt(m_trim_threshold, 8 << 20))
