"""Point-to-point exchange of variable-size byte messages with mpi4py buffer calls.

``exchange(comm, sends, sources)`` sends ``sends[dest]`` to each destination and receives one
message from each source: first the sizes (int64, uppercase Isend/Irecv), then the payloads
as uint8 numpy buffers. Messages to self are handed over without MPI. Bytes on the wire
(payloads plus the 8-byte size words) are counted into a :class:`FrameStats`.
"""

from __future__ import annotations

import numpy as np
from mpi4py import MPI

from ..core.stats import FrameStats

__all__ = ["exchange", "measure_bandwidth", "measure_memory_bandwidth", "max_over_ranks", "agree_all", "any_rank"]

_TAG_SIZE = 0x4D56
_TAG_DATA = 0x4D57


def exchange(comm, sends: dict[int, bytes], sources: list[int], stats: FrameStats | None = None, tag: int = 0) -> dict[int, np.ndarray]:
    me = comm.Get_rank()
    out: dict[int, np.ndarray] = {}
    remote_sources = [s for s in sources if s != me]
    sizes = {s: np.zeros(1, np.int64) for s in remote_sources}
    reqs = [comm.Irecv(sizes[s], source=s, tag=_TAG_SIZE + 2 * tag) for s in remote_sources]
    payloads = {d: np.frombuffer(b, np.uint8) for d, b in sends.items() if d != me}
    size_words = {d: np.array([p.size], np.int64) for d, p in payloads.items()}
    reqs += [comm.Isend(size_words[d], dest=d, tag=_TAG_SIZE + 2 * tag) for d in payloads]
    MPI.Request.Waitall(reqs)
    bufs = {s: np.empty(int(sizes[s][0]), np.uint8) for s in remote_sources}
    reqs = [comm.Irecv(bufs[s], source=s, tag=_TAG_DATA + 2 * tag) for s in remote_sources]
    reqs += [comm.Isend(p, dest=d, tag=_TAG_DATA + 2 * tag) for d, p in payloads.items()]
    MPI.Request.Waitall(reqs)
    out.update(bufs)
    if me in sends and me in sources:
        out[me] = np.frombuffer(sends[me], np.uint8)
    if stats is not None:
        stats.bytes_sent += sum(p.size + 8 for p in payloads.values())
        stats.bytes_recv += sum(b.size + 8 for b in bufs.values())
    return out


def measure_bandwidth(comm, nbytes: int = 8 << 20, repeat: int = 5) -> float:
    """Point-to-point bandwidth in bytes/s between ranks 0 and 1 (ping-pong of ``nbytes``
    uint8 buffers, best of ``repeat``); broadcast to every rank. 0.0 on a single rank."""
    if comm.Get_size() < 2:
        return 0.0
    buf = np.zeros(nbytes, np.uint8)
    best = float("inf")
    me = comm.Get_rank()
    for _ in range(repeat + 1):  # the first round trip warms up the connection
        comm.Barrier()
        t0 = MPI.Wtime()
        if me == 0:
            comm.Send(buf, dest=1, tag=77)
            comm.Recv(buf, source=1, tag=78)
        elif me == 1:
            comm.Recv(buf, source=0, tag=77)
            comm.Send(buf, dest=0, tag=78)
        best = min(best, (MPI.Wtime() - t0) / 2)
    return comm.bcast(nbytes / best if me == 0 else None, root=0)


def measure_memory_bandwidth(comm, nbytes: int = 64 << 20, repeat: int = 5) -> float:
    """Memory bandwidth in bytes/s (read + written) one rank gets while every rank of ``comm``
    copies ``nbytes`` at the same time (``np.copyto``; per repetition the slowest rank's time,
    best of ``repeat``): what each rank can count on when all of them composite together on
    shared cores and memory."""
    src = np.ones(nbytes, np.uint8)
    dst = np.zeros(nbytes, np.uint8)
    best = float("inf")
    for _ in range(repeat + 1):  # the first copy also faults the pages in
        comm.Barrier()
        t0 = MPI.Wtime()
        np.copyto(dst, src)
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
