"""A frame pipeline: each stage in its own thread, frames handed on synchronously.

The massive-model system (Revanth & Narayanan 2012, §3.3, Fig. 3) overlaps three modules:
while the server divides the frustum of frame i, each client's first GPU determines the
visibility of frame i−1 and its second GPU renders frame i−2. :class:`StagePipeline` is that
schedule for any list of stages inside one process (each stage may own its GL context):

* stage j runs in its own thread and takes frame f from stage j−1 through a **rendezvous**
  (:class:`Handoff`: ``put`` returns only once the next stage took the frame), so at most one
  frame is inside each stage — with k stages, k frames are in flight (the latency) and the
  period is the slowest stage's time;
* ``pipelined=False`` runs every frame through all stages before the next one starts (the
  synchronous reference: latency 1 frame, period = the sum of the stages);
* an exception in any stage stops all threads and is re-raised by :meth:`StagePipeline.run`.

Every stage execution is recorded (frame, stage, start, end in ``time.perf_counter`` seconds);
:func:`pipeline_metrics` turns records into period and latency figures.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

import numpy as np

__all__ = ["Handoff", "StageRecord", "StagePipeline", "pipeline_metrics"]

_POLL = 0.05


class _Stopped(Exception):
    pass


class Handoff:
    """A rendezvous channel between two stage threads: ``put`` blocks until ``get`` took it."""

    def __init__(self, stop: threading.Event):
        self._q: queue.Queue = queue.Queue(maxsize=1)
        self._taken = threading.Semaphore(0)
        self._stop = stop

    def put(self, item: Any) -> None:
        while True:
            if self._stop.is_set():
                raise _Stopped
            try:
                self._q.put(item, timeout=_POLL)
                break
            except queue.Full:
                continue
        while not self._taken.acquire(timeout=_POLL):
            if self._stop.is_set():
                raise _Stopped

    def get(self) -> Any:
        while True:
            if self._stop.is_set():
                raise _Stopped
            try:
                item = self._q.get(timeout=_POLL)
            except queue.Empty:
                continue
            self._taken.release()
            return item


@dataclass(frozen=True)
class StageRecord:
    frame: int
    stage: str
    start: float
    end: float


_END = object()


class StagePipeline:
    """stages: (name, fn) pairs; ``fn(frame, value) -> value`` (the first stage gets the input
    item). ``run(items)`` returns the last stage's outputs in frame order."""

    def __init__(self, stages: Sequence[tuple[str, Callable[[int, Any], Any]]], pipelined: bool = True):
        if not stages:
            raise ValueError("a pipeline needs at least one stage")
        self.stages = list(stages)
        self.pipelined = pipelined
        self.records: list[StageRecord] = []
        self._lock = threading.Lock()

    def _call(self, j: int, frame: int, value: Any) -> Any:
        name, fn = self.stages[j]
        t0 = time.perf_counter()
        out = fn(frame, value)
        rec = StageRecord(frame, name, t0, time.perf_counter())
        with self._lock:
            self.records.append(rec)
        return out

    def run(self, items: Iterable[Any]) -> list[Any]:
        self.records = []
        if not self.pipelined:
            outs = []
            for f, item in enumerate(items):
                for j in range(len(self.stages)):
                    item = self._call(j, f, item)
                outs.append(item)
            return outs
        return self._run_threads(list(items))

    def _run_threads(self, items: list[Any]) -> list[Any]:
        stop = threading.Event()
        k = len(self.stages)
        links = [Handoff(stop) for _ in range(k - 1)]
        outs: list[Any] = [None] * len(items)
        errors: list[BaseException] = []

        def worker(j: int) -> None:
            try:
                f = 0
                while True:
                    if j == 0:
                        if f == len(items):
                            value = _END
                        else:
                            value = (f, items[f])
                    else:
                        value = links[j - 1].get()
                    if value is _END:
                        if j < k - 1:
                            links[j].put(_END)
                        return
                    f, x = value
                    y = self._call(j, f, x)
                    if j < k - 1:
                        links[j].put((f, y))
                    else:
                        outs[f] = y
                    f += 1
            except _Stopped:
                return
            except BaseException as e:  # noqa: BLE001 - re-raised by run()
                errors.append(e)
                stop.set()

        threads = [threading.Thread(target=worker, args=(j,), name=f"massview-stage-{self.stages[j][0]}", daemon=True) for j in range(k)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            raise errors[0]
        return outs


def pipeline_metrics(records: Sequence[StageRecord], stages: Sequence[str], warmup: int = 2) -> dict:
    """Period (median interval between consecutive frames leaving the last stage), latency in
    frames (frames started in the first stage before a frame leaves the last one, counting
    itself; the max over frames) and in seconds, and mean time per stage."""
    first, last = stages[0], stages[-1]
    start = {r.frame: r.start for r in records if r.stage == first}
    end = {r.frame: r.end for r in records if r.stage == last}
    frames = sorted(end)
    ends = np.array([end[f] for f in frames])
    period = float(np.median(np.diff(ends[warmup:]))) if len(ends) > warmup + 1 else float("nan")
    in_flight = [sum(1 for g, s in start.items() if g >= f and s < end[f]) for f in frames]
    stage_ms = {s: 1e3 * float(np.mean([r.end - r.start for r in records if r.stage == s])) for s in stages}
    return {
        "period_s": period,
        "latency_frames": int(max(in_flight)) if in_flight else 0,
        "latency_s": float(np.median([end[f] - start[f] for f in frames])) if frames else float("nan"),
        "stage_ms": stage_ms,
    }
