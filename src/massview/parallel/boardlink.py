"""Non-blocking messages between the visualization rank and the Reliefboard backends (§6).

The visualization rank must never wait for a backend, so its side of the link uses only
non-blocking point-to-point calls: requests leave with ``isend`` (small pickled records),
boards are found with a matched probe (``Improbe``, the race-free ``Iprobe``) and received
into numpy byte buffers with ``Irecv``, completed with ``Test`` in later frames. No collective
involves the backends while frames run, so a slow or stalled backend delays only the requests
assigned to it.

Backends may block (they have nothing else to do): they poll for requests, build boards and
send them back with ``Isend``. Shutdown: the visualization rank sends STOP to every backend;
a backend answers with an empty board message (``DONE``) after its last board, so the
visualization rank drains every board still on the way before it returns — no message is left
unmatched at ``MPI_Finalize``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

__all__ = ["BoardRequest", "VisualizationLink", "BackendLink", "TAG_REQUEST", "TAG_BOARD", "TAG_STOP"]

TAG_REQUEST, TAG_BOARD, TAG_STOP = 0x4D21, 0x4D22, 0x4D23


@dataclass(frozen=True)
class BoardRequest:
    """One board request: object id, unit direction observer → object centre (3 floats),
    resolution in pixels, and a serial number unique on the visualization rank."""

    object_id: int
    direction: tuple
    size: int
    serial: int


class VisualizationLink:
    """The visualization rank's end: ``send`` requests, ``poll`` arrived boards; never blocks
    until :meth:`close`."""

    def __init__(self, comm, backends: list[int]):
        self.comm = comm
        self.backends = list(backends)
        self._sends: list = []
        self._recvs: list[tuple[MPI.Request, np.ndarray, int]] = []
        self.bytes_sent = 0
        self.bytes_recv = 0

    def send(self, backend: int, request: BoardRequest) -> None:
        self._sends.append(self.comm.isend(request, dest=backend, tag=TAG_REQUEST))
        self.bytes_sent += 64  # a pickled request is ~60 bytes; counted, not measured

    def _post_receives(self) -> None:
        """Post a receive for every board message that has arrived. A probe that finds nothing
        may still have pulled a message in (MPICH probes match before they progress), so
        probing stops only after two misses in a row."""
        status = MPI.Status()
        misses = 0
        while misses < 2:
            msg = self.comm.Improbe(source=MPI.ANY_SOURCE, tag=TAG_BOARD, status=status)
            if msg is None:
                misses += 1
                continue
            misses = 0
            buf = np.empty(status.Get_count(MPI.BYTE), np.uint8)
            self._recvs.append((msg.Irecv([buf, MPI.BYTE]), buf, status.Get_source()))

    def poll(self) -> list[tuple[int, bytes]]:
        """Boards that have arrived completely, as ``(backend rank, bytes)``; an empty payload is
        a backend's DONE marker."""
        self._sends = [r for r in self._sends if not r.Test()]
        self._post_receives()
        done, waiting = [], []
        for req, buf, src in self._recvs:
            if req.Test():
                done.append((src, buf.tobytes()))
                self.bytes_recv += buf.size
            else:
                waiting.append((req, buf, src))
        self._recvs = waiting
        return done

    def close(self) -> list[tuple[int, bytes]]:
        """Stop every backend and drain what they still send; returns the boards drained."""
        stops = [self.comm.isend(None, dest=b, tag=TAG_STOP) for b in self.backends]
        open_backends = set(self.backends)
        late = []
        while open_backends:
            for src, data in self.poll():
                if data:
                    late.append((src, data))
                else:
                    open_backends.discard(src)
            time.sleep(0.001)
        MPI.Request.Waitall(stops + self._sends)
        self._sends = []
        return late


class BackendLink:
    """A backend's end: ``requests()`` drains what arrived, ``send_board`` answers."""

    def __init__(self, comm, viz: int = 0):
        self.comm = comm
        self.viz = viz
        self._sends: list[tuple[MPI.Request, np.ndarray]] = []
        self.stopped = False

    def requests(self) -> list[BoardRequest]:
        """All requests that arrived so far (sets ``stopped`` on STOP); never blocks."""
        out = []
        status = MPI.Status()
        misses = 0
        while misses < 2 and not self.stopped:  # two misses: see VisualizationLink._post_receives
            if not self.comm.Iprobe(source=self.viz, tag=MPI.ANY_TAG, status=status):
                misses += 1
                continue
            misses = 0
            msg = self.comm.recv(source=self.viz, tag=status.Get_tag())
            if status.Get_tag() == TAG_STOP:
                self.stopped = True
            else:
                out.append(msg)
        self._sends = [(r, b) for r, b in self._sends if not r.Test()]
        return out

    def send_board(self, data: bytes) -> None:
        buf = np.frombuffer(data, np.uint8).copy()
        self._sends.append((self.comm.Isend([buf, MPI.BYTE], dest=self.viz, tag=TAG_BOARD), buf))

    def close(self) -> None:
        """After STOP: the DONE marker, then wait for every board sent."""
        self.send_board(b"")
        MPI.Request.Waitall([r for r, _ in self._sends])
        self._sends = []
