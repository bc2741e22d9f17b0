"""The per-frame loop every system shares: plan → render → composite → deliver → record.

Each frame, rank 0 (the destination) fixes the camera and plans one :class:`Task` per rank;
both are broadcast. Every rank renders its task. Sort-first tiles already are final pixels;
sort-last full-frame images are depth-composited (direct-send, binary-swap or radix-k). The
final pixels are delivered to the display tiles — rank 0's whole frame, or each wall rank's
own tile — and handed to ``sink(frame, tile_image)`` on display ranks. With ``reference`` each
display rank also renders the serial image alone and records how its tile differs. Per-rank
:class:`FrameStats` are gathered to rank 0.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from ..core.camera import Camera, Viewport
from ..core.config import RenderConfig
from ..core.errors import MassviewError
from ..core.image import Image, blank_image
from ..core.stats import FrameStats
from ..parallel.composite import composite, deliver, final_regions
from ..parallel.decompose import parse_decomposition, parse_wall
from ..parallel.exchange import Outbox
from ..render.meshes import rank_tint

__all__ = ["FrameResult", "SinkThread", "display_tiles", "render_frame", "render_frames"]


class InjectedFault(MassviewError, RuntimeError):
    """Raised on purpose by ``--fault RANK:FRAME`` (tests of failure handling)."""


@dataclass
class FrameResult:
    stats: FrameStats
    tile: Image | None  # this rank's display tile, None on non-display ranks
    diff: tuple[int, int, int] | None = None  # (max abs diff, differing pixels, pixels) vs serial


class SinkThread:
    """A frame sink (``sink(frame, image)``, e.g. writing PNGs) run on its own thread, so the
    caller's frame period does not include it. Calls queue up to ``depth`` frames (a full queue
    blocks the caller: memory stays bounded); frames reach ``sink`` in call order. An error in
    ``sink`` is re-raised on the caller's thread by the next call or by :meth:`close` (later
    frames are then dropped). Use as a context manager or call :meth:`close`; the images handed
    over must not be changed afterwards."""

    _STOP = object()

    def __init__(self, sink: Callable[[int, Image], None], depth: int = 4):
        if depth < 1:
            raise MassviewError(f"SinkThread depth must be at least 1, got {depth}")
        self._sink = sink
        self._q: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="massview-sink", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is self._STOP:
                return
            if self._error is None:
                try:
                    self._sink(*item)
                except BaseException as e:  # noqa: BLE001 - re-raised on the caller's thread
                    self._error = e

    def _raise(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    def __call__(self, frame: int, image: Image) -> None:
        if self._closed:
            raise MassviewError("SinkThread: called after close()")
        self._raise()
        self._q.put((frame, image))

    def close(self) -> None:
        """Wait until every queued frame went through the sink; re-raise its error, if any."""
        if not self._closed:
            self._closed = True
            self._q.put(self._STOP)
            self._thread.join()
        self._raise()

    def __enter__(self) -> "SinkThread":
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()
        else:  # the caller's own error wins; still let the thread finish
            try:
                self.close()
            except BaseException:  # noqa: BLE001
                pass


def display_tiles(cfg: RenderConfig, nranks: int) -> list[tuple[int, Viewport]]:
    if cfg.wall:
        return list(enumerate(parse_wall(cfg.wall, nranks, cfg.width, cfg.height)))
    return [(0, Viewport(0, 0, cfg.width, cfg.height))]


def _check_fault(cfg: RenderConfig, rank: int, frame: int) -> None:
    if cfg.fault:
        r, _, f = cfg.fault.partition(":")
        if int(r) == rank and int(f or 0) == frame:
            raise InjectedFault(f"injected fault at frame {frame} (--fault {cfg.fault})")


def image_diff(a: Image, b: Image) -> tuple[int, int, int]:
    d = np.abs(a.color.astype(np.int16) - b.color.astype(np.int16)).max(axis=2)
    return int(d.max(initial=0)), int(np.count_nonzero(d)), int(d.size)


def _begin(comm, system, cfg: RenderConfig, camera: Camera | None, frame: int, stats: FrameStats):
    """Camera, LOD, plan and draw of one frame (main thread: GL and collectives on ``comm``).
    Returns (camera, this rank's image)."""
    rank, n = comm.Get_rank(), comm.Get_size()
    camera = comm.bcast(camera, root=0)
    if hasattr(system, "prepare_frame"):  # per-frame LOD shared by all ranks (terrain)
        system.prepare_frame(comm, camera, cfg, stats)
    with stats.stage("lod"):
        tasks = comm.bcast(system.plan(camera, cfg, n) if rank == 0 else None, root=0)
    _check_fault(cfg, rank, frame)
    tint = rank_tint(rank) if cfg.color_by_rank else (0, 0, 0, 0)
    vp = getattr(tasks[rank], "viewport", None)
    if vp is not None and (vp.w <= 0 or vp.h <= 0):  # a sort-first tile with no pixels (a tiny --size split among
        return camera, blank_image(vp)                # more ranks than it has rows or columns): nothing to draw
    return camera, system.render(tasks[rank], camera, cfg, stats, tint)


def _finish(comm, system, cfg: RenderConfig, camera: Camera, image: Image, stats: FrameStats) -> Image | None:
    """Composite (sort-last) and deliver one frame, then the system's display-side touches on the
    final pixels (``system.finish``, terrain: the sky; numpy only, timed as stage ``finish``);
    only point-to-point calls on ``comm`` (sort-first: also one allgather of the tiles; sort-last
    ranks compute where every region is), no GL: safe on the communication thread with its own
    ``comm``."""
    kind, _ = parse_decomposition(cfg.decomposition, system.sort_last_modes)
    regions, frame = None, None  # sort-first: each rank's tile, allgathered by deliver
    box = Outbox(comm, stats)  # compositing's sends stay in flight until deliver's end
    if kind == "sort-last":  # the read-back is this frame's own: compositing and the display tile reuse its buffers
        piece, frame = composite(comm, image, cfg.compositor, cfg.radix_k, stats, cfg.codec, box, owned=True), image
        regions = final_regions(comm.Get_size(), cfg.compositor, cfg.radix_k, image.viewport)
    else:
        piece = image
    tile = deliver(comm, piece, display_tiles(cfg, comm.Get_size()), stats, cfg.codec, regions, box, frame)
    if tile is not None and hasattr(system, "finish"):
        with stats.stage("finish"):
            tile = system.finish(camera, cfg, tile)
        stats.count("finished_pixels", tile.viewport.area)
    return tile


def render_frame(comm, system, cfg: RenderConfig, camera: Camera | None, frame: int,
                 sink: Callable[[int, Image], None] | None = None) -> FrameResult:
    """Render one frame on every rank of ``comm``; ``camera`` matters on rank 0 only."""
    if hasattr(system, "render_frame"):  # systems with roles (T2, M1, M2) run their own per-role frame
        return system.render_frame(comm, cfg, camera, frame, sink)
    stats = FrameStats(frame=frame, rank=comm.Get_rank())
    with stats.stage("total"):
        camera, image = _begin(comm, system, cfg, camera, frame, stats)
        tile = _finish(comm, system, cfg, camera, image, stats)
    result = FrameResult(stats, tile)
    if tile is not None:
        if sink is not None:
            sink(frame, tile)
        if cfg.reference:
            ref = system.render_reference(camera, cfg).crop(tile.viewport)
            result.diff = image_diff(tile, ref)
    return result


def render_frames(comm, system, cfg: RenderConfig, cameras, sink: Callable[[int, Image], None] | None = None,
                  frames: int | None = None) -> Iterator[FrameResult]:
    """Render ``frames`` frames (default ``cfg.frames``; ``cameras[f]`` on rank 0, ignored elsewhere) and yield
    their results in frame order, on every rank in the same order (callers may run
    collectives on ``comm`` between results). ``cfg.pipeline == "off"``: one
    :func:`render_frame` after the other; ``"on"``: :class:`~.pipeline.FramePipeline` (systems
    with roles, which bring their own ``render_frame``, always run one frame after the other)."""
    camera_of = (lambda f: cameras[f]) if comm.Get_rank() == 0 else (lambda f: None)
    frames = cfg.frames if frames is None else frames
    if cfg.pipeline == "off" or hasattr(system, "render_frame"):  # systems with roles run their own loop
        for f in range(frames):
            yield render_frame(comm, system, cfg, camera_of(f), f, sink)
        return
    from .pipeline import FramePipeline

    with FramePipeline(comm, system, cfg, sink) as pipe:
        for f in range(frames):
            yield from pipe.submit(camera_of(f), f)
        yield from pipe.drain()
