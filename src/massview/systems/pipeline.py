"""The pipelined frame loop: frame i is composited and delivered while frame i+1 is drawn.

The main thread keeps everything that needs the GL context or the world communicator: the
camera broadcast, the LOD (with its residency agreement), the plan and the draw and readback
(``frameloop._begin``). It then hands the frame's image to a communication thread, which runs
compositing and delivery (``frameloop._finish``: point-to-point messages and one allgather)
on its own duplicate of the communicator — so the two threads' collectives never interleave
on one communicator — and hands the tile to the sink. MPI runs at ``MPI_THREAD_MULTIPLE``
(mpi4py's default; the mpich wheel provides it), mpi4py releases the GIL in blocking calls and
numpy inside its large loops, so the communication thread runs while the main thread waits in
MPI or numpy or runs Python. moderngl keeps the GIL inside its GL calls, so the wait for
llvmpipe's raster threads to draw the frame — most of a frame's draw stage — goes through
``render.context.finish`` (``glFinish`` through ctypes, which releases the GIL) instead of
``ctx.finish()``: the compositing thread runs during that wait. ``massview bench frame``
measures this (its GIL probe) and how busy the synchronous loop keeps the cores, which bounds
what the pipelined loop can gain on a 2-core llvmpipe machine.

At most ``in_flight`` frames are between "drawing started" and "delivered" (default 2: one
being composited, one being drawn); results come back in frame order, and every rank waits at
the same points, so callers may run collectives on the world communicator between results
(``render_cmd`` gathers statistics there). Images do not change: each frame's image, LOD and
reference are fixed on the main thread before the next frame begins. A frame's ``total`` is
its latency (draw start to delivery); throughput is frames over wall time.

This is the distributed rendering pipeline of M1 (Revanth & Narayanan 2012, §3.3: culling,
rendering and assembly of different frames run at once), here between the stages of one rank.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from dataclasses import dataclass

from ..core.camera import Camera
from ..core.config import RenderConfig
from ..core.image import Image
from ..core.stats import FrameStats
from .frameloop import FrameResult, _begin, _finish, display_tiles, image_diff

__all__ = ["FramePipeline", "IN_FLIGHT"]

IN_FLIGHT = 2


@dataclass
class _Job:
    frame: int
    camera: Camera
    stats: FrameStats
    image: Image
    reference: Image | None
    t0: float


class FramePipeline:
    """Submit frames in order with :meth:`submit`; it returns the results that had to finish
    first (to keep at most ``in_flight`` frames in flight); :meth:`drain` returns the rest.
    Use as a context manager so the communication thread ends."""

    def __init__(self, comm, system, cfg: RenderConfig, sink=None, in_flight: int = IN_FLIGHT):
        self.comm, self.system, self.cfg, self.sink = comm, system, cfg, sink
        self.in_flight = max(1, in_flight)
        self._display = any(r == comm.Get_rank() for r, _ in display_tiles(cfg, comm.Get_size()))
        self._ccomm = comm.Dup()  # the communication thread's own communicator
        self._jobs: queue.Queue = queue.Queue()
        self._done: queue.Queue = queue.Queue()
        self._pending: deque[int] = deque()
        self._thread = threading.Thread(target=self._loop, name="massview-composite", daemon=True)
        self._thread.start()

    def submit(self, camera: Camera | None, frame: int) -> list[FrameResult]:
        out = []
        while len(self._pending) >= self.in_flight:
            out.append(self._next())
        stats = FrameStats(frame=frame, rank=self.comm.Get_rank())
        t0 = time.perf_counter()
        camera, image = _begin(self.comm, self.system, self.cfg, camera, frame, stats)
        reference = self.system.render_reference(camera, self.cfg) if self.cfg.reference and self._display else None
        self._pending.append(frame)
        self._jobs.put(_Job(frame, camera, stats, image, reference, t0))
        return out

    def drain(self) -> list[FrameResult]:
        return [self._next() for _ in range(len(self._pending))]

    def _next(self) -> FrameResult:
        result = self._done.get()
        self._pending.popleft()
        if isinstance(result, BaseException):
            raise result
        return result

    def _loop(self) -> None:
        while (job := self._jobs.get()) is not None:
            try:
                self._done.put(self._complete(job))
            except BaseException as e:  # noqa: BLE001 - handed to the main thread, which re-raises
                self._done.put(e)
                return

    def _complete(self, job: _Job) -> FrameResult:
        tile = _finish(self._ccomm, self.system, self.cfg, job.camera, job.image, job.stats)
        job.stats.times_ms["total"] += (time.perf_counter() - job.t0) * 1e3
        result = FrameResult(job.stats, tile)
        if tile is not None:
            if self.sink is not None:
                self.sink(job.frame, tile)
            if job.reference is not None:
                result.diff = image_diff(tile, job.reference.crop(tile.viewport))
        return result

    def close(self, clean: bool = True) -> None:
        self._jobs.put(None)
        if clean:  # after a failure the thread may sit in MPI; the runtime aborts every rank
            self._thread.join()
            self._ccomm.Free()

    def __enter__(self) -> "FramePipeline":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(clean=exc_type is None)
