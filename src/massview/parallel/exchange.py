"""Point-to-point exchange of variable-size byte messages with mpi4py buffer calls.

``exchange(comm, sends, sources)`` sends ``sends[dest]`` to each destination and receives one
message from each source as uint8 numpy buffers (uppercase Isend, matched probe and receive:
one message per pair, its size read from the probe). Messages to self are handed over
without MPI. Bytes on the wire (payloads) are counted into a :class:`FrameStats`.
"""

from __future__ import annotations

import numpy as np
from mpi4py import MPI

from ..core.stats import FrameStats

__all__ = ["exchange", "measure_bandwidth", "measure_memory_bandwidth", "max_over_ranks", "agree_all", "any_rank"]

_TAG_DATA = 0x4D57


def exchange(comm, sends: dict[int, bytes], sources: list[int], stats: FrameStats | None = None, tag: int = 0) -> dict[int, np.ndarray]:
    """Send ``sends[dest]`` to each destination and receive one message from each of
    ``sources``; returns {source: uint8 array}. One message per pair and no size round: the
    payloads go out first (``Isend``), then each source's message is matched with ``Mprobe``,
    sized from its status and received with ``Mrecv`` into a buffer of that size. A wait is
    where a rank gives its core to a peer on a shared machine (see
    :func:`massview.parallel.runtime.launch_env`), so one wait per peer instead of two halves
    the scheduling delays of a round."""
    me = comm.Get_rank()
    out: dict[int, np.ndarray] = {}
    payloads = {d: np.frombuffer(b, np.uint8) for d, b in sends.items() if d != me}
    reqs = [comm.Isend(p, dest=d, tag=_TAG_DATA + 2 * tag) for d, p in payloads.items()]
    status = MPI.Status()
    for s in (s for s in sources if s != me):
        msg = comm.Mprobe(source=s, tag=_TAG_DATA + 2 * tag, status=status)
        buf = np.empty(status.Get_count(MPI.BYTE), np.uint8)
        msg.Recv(buf)
        out[s] = buf
    MPI.Request.Waitall(reqs)
    if me in sends and me in sources:
        out[me] = np.frombuffer(sends[me], np.uint8)
    if stats is not None:
        stats.bytes_sent += sum(p.size for p in payloads.values())
        stats.bytes_recv += sum(b.size for s, b in out.items() if s != me)
    return out


def measure_bandwidth(comm, nbytes: int = 8 << 20, repeat: int = 5) -> float:
    """Point-to-point bandwidth in bytes/s one rank can count on while every rank exchanges at
    once: ranks (2i, 2i+1) swap ``nbytes`` uint8 buffers (``Sendrecv``; with an odd count the
    last rank sits out), timed from a common barrier until the last pair is done (a barrier),
    best of ``repeat``; the same on every rank. 0.0 on a single rank. Ranks that share cores
    share them here as they do when they composite (issue 20: an honest floor)."""
    n, me = comm.Get_size(), comm.Get_rank()
    if n < 2:
        return 0.0
    send, recv = np.ones(nbytes, np.uint8), np.zeros(nbytes, np.uint8)
    partner = me ^ 1
    best = float("inf")
    for _ in range(repeat + 1):  # the first exchange warms up the connection and the pages
        comm.Barrier()
        t0 = MPI.Wtime()
        if partner < n:
            comm.Sendrecv(send, dest=partner, sendtag=77, recvbuf=recv, source=partner, recvtag=77)
        comm.Barrier()
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
        comm.Barrier()
        t0 = MPI.Wtime()
        np.copyto(dst, src)
        comm.Barrier()
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
