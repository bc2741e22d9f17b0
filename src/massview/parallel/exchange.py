"""Point-to-point exchange of variable-size byte messages with mpi4py buffer calls.

Messages are uint8 buffers sent with uppercase ``Isend`` and received one per pair with a
matched probe (``Mprobe``: its size comes from the status, so there is no size round) and
``Recv`` into a buffer of that size. :class:`Outbox` sends each message the moment it is
encoded and waits for all of them once, at the end, so a rank never blocks on a send while it
has work of its own; :func:`receive` / :func:`receive_any` take one message where the caller
needs it (a rank does its local work first and waits for a peer only when it has nothing else
to do). :func:`exchange` is the one-call form. Bytes on the wire (payloads) are counted into a
:class:`FrameStats`.

**How a rank waits** (``MASSVIEW_MPI_WAIT``, read here; :func:`set_wait_mode` overrides it):

* ``poll`` (MPICH's own blocking calls: ``Waitall``, ``Mprobe``, ``Barrier``): MPICH
  busy-polls, so a waiting rank keeps its core. Best while every rank has a core of its own.
* ``sleep``: the same waits made of non-blocking calls (``Testall``, ``Improbe`` + ``Irecv``,
  ``Ibarrier``) polled back to back for 50 µs, then with sleeps in between, 20 µs doubling
  to 160 µs, with this thread's timer slack set to 1 ns (``prctl(PR_SET_TIMERSLACK)``) so
  that a short sleep stays short.
  A waiting rank gives its core to the peer it waits for when ranks outnumber the cores
  (issue 20; :func:`massview.parallel.runtime.launch_env` picks it then). The messages and
  their order are the same in both modes: only how a rank waits for them differs.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np
from mpi4py import MPI

from ..core.errors import ConfigError
from ..core.stats import FrameStats

__all__ = ["Outbox", "receive", "receive_any", "receive_into", "exchange", "measure_bandwidth", "measure_memory_bandwidth",
           "max_over_ranks", "agree_all", "any_rank", "WAIT_MODES", "WAIT_ENV_VAR", "wait_mode", "set_wait_mode", "wait_all",
           "sleep_until", "barrier"]

WAIT_MODES = ("poll", "sleep")
WAIT_ENV_VAR = "MASSVIEW_MPI_WAIT"
_SPIN_S, _SLEEP_FIRST_S, _SLEEP_MAX_S = 50e-6, 20e-6, 160e-6
_mode: list[str | None] = [None]  # None: not read from the environment yet


def _check_mode(mode: str, where: str) -> str:
    if mode not in WAIT_MODES:
        raise ConfigError(f"{where}={mode!r} is not a wait mode; use one of {', '.join(WAIT_MODES)}")
    return mode


def wait_mode() -> str:
    """How this process waits for peers: ``MASSVIEW_MPI_WAIT`` (default ``poll``) unless
    :func:`set_wait_mode` chose otherwise."""
    if _mode[0] is None:
        _mode[0] = _check_mode(os.environ.get(WAIT_ENV_VAR, "poll") or "poll", WAIT_ENV_VAR)
    return _mode[0]


def set_wait_mode(mode: str) -> str:
    """Make every later wait of this process use ``mode``; returns the previous mode. Every
    rank of a communicator should use the same mode (the messages do not depend on it)."""
    before = wait_mode()
    _mode[0] = _check_mode(mode, "wait mode")
    return before


_SLACK = threading.local()


def _low_timer_slack() -> None:
    """Set this thread's timer slack to 1 ns once (Linux; elsewhere nothing): with the
    kernel's default 50 µs slack a 20 µs ``time.sleep`` took 119 µs, with 1 ns 60 µs (under
    load)."""
    if getattr(_SLACK, "done", False):
        return
    _SLACK.done = True
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK, 1 ns
    except (OSError, AttributeError):
        pass


def sleep_until(done, spin_s: float = _SPIN_S, first_s: float = _SLEEP_FIRST_S, max_s: float = _SLEEP_MAX_S,
                low_slack: bool = True):
    """Call ``done()`` until it returns something true, and return that: for ``spin_s`` back to
    back, then with sleeps in between (``first_s`` doubling to ``max_s``), with this thread's
    timer slack at 1 ns when ``low_slack``. The defaults are the ``sleep`` wait mode's: a 50 µs
    spin (a peer that is running answers within that; without it, 2 ranks took 1.17× poll's
    time, under load), then 20 µs doubling to 160 µs."""
    out = done()
    if out:
        return out
    t_end = time.perf_counter() + spin_s
    while time.perf_counter() < t_end:
        out = done()
        if out:
            return out
    if low_slack:
        _low_timer_slack()
    delay = first_s
    while True:
        time.sleep(delay)
        out = done()
        if out:
            return out
        delay = min(2 * delay, max_s)


def wait_all(requests: list) -> None:
    """Complete every request (``Waitall``, or ``Testall`` between sleeps: :func:`wait_mode`)."""
    if not requests:
        return
    if wait_mode() == "sleep":
        sleep_until(lambda: MPI.Request.Testall(requests))
    else:
        MPI.Request.Waitall(requests)


def barrier(comm) -> None:
    """``comm``'s barrier, waited for the :func:`wait_mode` way."""
    if wait_mode() == "sleep":
        wait_all([comm.Ibarrier()])
    else:
        comm.Barrier()

_TAG_DATA = 0x4D57


def _tag(tag: int) -> int:
    return _TAG_DATA + 2 * tag


class Outbox:
    """This rank's messages in flight: :meth:`send` starts each at once (``Isend``; the buffer
    is kept alive here), :meth:`wait` completes them all."""

    def __init__(self, comm, stats: FrameStats | None = None):
        self.comm, self.stats = comm, stats
        self._reqs: list = []
        self._bufs: list = []

    def send(self, dest: int, data, tag: int) -> None:
        buf = np.frombuffer(data, np.uint8)
        self._bufs.append(buf)
        self._reqs.append(self.comm.Isend(buf, dest=dest, tag=_tag(tag)))
        if self.stats is not None:
            self.stats.bytes_sent += buf.size

    def wait(self) -> None:
        wait_all(self._reqs)
        self._reqs, self._bufs = [], []


def receive(comm, source: int, tag: int, stats: FrameStats | None = None) -> np.ndarray:
    """The next message from ``source`` with ``tag`` (as sent by :class:`Outbox`), uint8."""
    return receive_any(comm, tag, stats, source)[1]


def receive_any(comm, tag: int, stats: FrameStats | None = None, source: int = MPI.ANY_SOURCE) -> tuple[int, np.ndarray]:
    """(source, message) of the first message with ``tag`` to arrive from any rank (or from
    ``source``): matched probe, sized from its status, received into a new uint8 buffer."""
    status = MPI.Status()
    if wait_mode() == "sleep":
        msg = sleep_until(lambda: comm.Improbe(source=source, tag=_tag(tag), status=status))
        buf = np.empty(status.Get_count(MPI.BYTE), np.uint8)
        wait_all([msg.Irecv(buf)])
    else:
        msg = comm.Mprobe(source=source, tag=_tag(tag), status=status)
        buf = np.empty(status.Get_count(MPI.BYTE), np.uint8)
        msg.Recv(buf)
    if stats is not None:
        stats.bytes_recv += buf.size
    return status.Get_source(), buf


def receive_into(comm, buf: np.ndarray, source: int, tag: int, stats: FrameStats | None = None):
    """Start receiving the message with ``tag`` from ``source`` straight into ``buf`` (a
    contiguous array whose size the sender matches exactly, as :meth:`Outbox.send` of an
    array of the same shape); returns the request (complete it with :func:`wait_all`)."""
    view = buf.reshape(-1).view(np.uint8)
    if stats is not None:
        stats.bytes_recv += view.size
    return comm.Irecv(view, source=source, tag=_tag(tag))


def exchange(comm, sends: dict[int, bytes], sources: list[int], stats: FrameStats | None = None, tag: int = 0) -> dict[int, np.ndarray]:
    """Send ``sends[dest]`` to each destination and receive one message from each of
    ``sources``; returns {source: uint8 array}. Messages to self are handed over without MPI."""
    me = comm.Get_rank()
    box = Outbox(comm, stats)
    for d, b in sends.items():
        if d != me:
            box.send(d, b, tag)
    out = {s: receive(comm, s, tag, stats) for s in sources if s != me}
    box.wait()
    if me in sends and me in sources:
        out[me] = np.frombuffer(sends[me], np.uint8)
    return out


def measure_bandwidth(comm, nbytes: int = 8 << 20, repeat: int = 5) -> float:
    """Point-to-point bandwidth in bytes/s one rank can count on while every rank exchanges at
    once: ranks (2i, 2i+1) swap ``nbytes`` uint8 buffers (``Isend`` + ``Irecv``, waited for
    the :func:`wait_mode` way, as compositing waits; with an odd count the last rank sits
    out), timed from a common barrier until the last pair is done (a barrier),
    best of ``repeat``; the same on every rank. 0.0 on a single rank. Ranks that share cores
    share them here as they do when they composite (issue 20: an honest floor)."""
    n, me = comm.Get_size(), comm.Get_rank()
    if n < 2:
        return 0.0
    send, recv = np.ones(nbytes, np.uint8), np.zeros(nbytes, np.uint8)
    partner = me ^ 1
    best = float("inf")
    for _ in range(repeat + 1):  # the first exchange warms up the connection and the pages
        barrier(comm)
        t0 = MPI.Wtime()
        if partner < n:
            wait_all([comm.Irecv(recv, source=partner, tag=77), comm.Isend(send, dest=partner, tag=77)])
        barrier(comm)
        best = min(best, max_over_ranks(comm, MPI.Wtime() - t0))
    return nbytes / best


def measure_memory_bandwidth(comm, nbytes: int = 64 << 20, repeat: int = 5) -> float:
    """Memory bandwidth in bytes/s (read + written) one rank can count on while every rank of
    ``comm`` copies ``nbytes`` at the same time (``np.copyto``), timed from a common barrier
    until the last rank is done (a barrier), best of ``repeat``. Timing each rank's own copy
    instead would let ranks that a shared core runs one after the other each look as fast as
    a rank alone: on 4 ranks over 2 cores that doubled the figure and halved the floor."""
    src = np.ones(nbytes, np.uint8)
    dst = np.zeros(nbytes, np.uint8)
    best = float("inf")
    for _ in range(repeat + 1):  # the first copy also faults the pages in
        barrier(comm)
        t0 = MPI.Wtime()
        np.copyto(dst, src)
        barrier(comm)
        best = min(best, max_over_ranks(comm, MPI.Wtime() - t0))
    return 2 * nbytes / best


def max_over_ranks(comm, value: float) -> float:
    """The maximum of ``value`` over all ranks (e.g. a stage time: the slowest rank sets it)."""
    return comm.allreduce(value, op=MPI.MAX)


def agree_all(comm, flags: np.ndarray) -> np.ndarray:
    """Element-wise AND of a boolean array over all ranks (e.g. blocks resident everywhere)."""
    if comm.Get_size() == 1:
        return flags
    mine = np.ascontiguousarray(flags, dtype=np.uint8)
    out = np.empty_like(mine)
    comm.Allreduce(mine, out, op=MPI.BAND)
    return out.astype(bool)


def any_rank(comm, flag: bool) -> bool:
    return bool(comm.allreduce(bool(flag), op=MPI.LOR))


_POLITE_TAG = 7707


def polite_bcast(comm, obj=None, root: int = 0, longest_sleep: float = 0.01):
    """``comm.bcast(obj, root)`` without spinning: the root sends the pickled object to every
    rank, the others test for it and sleep between tests, from 0.2 ms up to ``longest_sleep``
    (an MPI bcast busy-polls a core for as long as the root takes to come: a viewer with nobody
    watching kept its ranks at 40–75 % CPU). For loops whose root may be slow to come."""
    if comm.Get_size() == 1:
        return obj
    if comm.Get_rank() == root:
        reqs = [comm.isend(obj, dest=r, tag=_POLITE_TAG) for r in range(comm.Get_size()) if r != root]
        nap = 2e-4
        while reqs:
            reqs = [r for r in reqs if not r.Test()]
            if reqs:
                time.sleep(nap)
                nap = min(nap * 2, longest_sleep)
        return obj
    req, nap = comm.irecv(source=root, tag=_POLITE_TAG), 2e-4
    while True:
        done, value = req.test()
        if done:
            return value
        time.sleep(nap)
        nap = min(nap * 2, longest_sleep)
