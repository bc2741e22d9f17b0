"""Server ↔ client messages of the massive-model system (M1): over MPI between the roles,
or through queues when the server and its single client share one process."""

from __future__ import annotations

import os
import queue
import threading

import numpy as np

from ..core.errors import ConfigError
from ..parallel.exchange import sleep_until
from ..parallel.roles import Role
from ..parallel.runtime import say_rank_error
from .dmmr_client import ClientTask

__all__ = ["ROLES", "MpiLink", "LocalLink"]

_TAG_TASK, _TAG_SIZE, _TAG_IMAGE = 0x4D31, 0x4D32, 0x4D33


ROLES = (Role("server", 1), Role("client", None, minimum=1))

#: how a waiting role polls: sleep between polls, from 50 µs doubling to 1 ms (MPICH's blocking
#: calls spin; five processes on two cores would steal the cores the busy ones need).
#: ``MASSVIEW_DMMR_WAIT=spin`` restores the blocking calls (the before/after measurement).
_BACKOFF = (50e-6, 1e-3)


def _sleeping() -> bool:
    mode = os.environ.get("MASSVIEW_DMMR_WAIT") or "sleep"
    if mode not in ("sleep", "spin"):
        raise ConfigError(f"MASSVIEW_DMMR_WAIT={mode!r} is not a wait mode; use sleep (the default) or spin")
    return mode == "sleep"


def wait_until(ready) -> None:
    """Call ``ready()`` until it returns true, sleeping 50 µs → 1 ms (doubling) between calls
    (no spin, the default timer slack)."""
    sleep_until(ready, spin_s=0.0, first_s=_BACKOFF[0], max_s=_BACKOFF[1], low_slack=False)


class MpiLink:
    """Server ↔ client messages over the roles' parent communicator: tasks pickled (lowercase
    calls), sub-frames as uint8 buffers (uppercase). Sends are non-blocking, so a stage never
    waits for the receiver: at most three frames' worth of sends per sender are in flight
    (older ones are completed first), and ``flush`` completes the rest. Waits sleep between
    polls (:func:`wait_until`: ``Iprobe`` before a receive, ``Test`` for a send's completion)
    instead of spinning in MPI's blocking calls."""

    def __init__(self, rc):
        self.comm, self.server, self.clients = rc.parent, rc.leader("server"), rc.ranks["client"]
        self._OUTSTANDING = 3 * len(self.clients) + 1 if rc.role == "server" else 4
        self._sent: list = []  # (request(s), buffers kept alive until complete)
        self._lock = threading.Lock()
        self.sleeping = _sleeping()

    def _complete(self, reqs) -> None:
        for r in reqs:
            if self.sleeping:
                wait_until(r.Test)
            else:
                r.wait()

    def _arrived(self, source: int, tag: int) -> None:
        """Return once a message from ``source`` with ``tag`` can be received (sleeping polls)."""
        if self.sleeping:
            wait_until(lambda: self.comm.Iprobe(source=source, tag=tag))

    def _track(self, reqs: list, keep) -> None:
        with self._lock:
            self._sent.append((reqs, keep))
            old, self._sent = self._sent[:-self._OUTSTANDING], self._sent[-self._OUTSTANDING:]
        for rs, _ in old:
            self._complete(rs)

    def flush(self) -> None:
        with self._lock:
            old, self._sent = self._sent, []
        for rs, _ in old:
            self._complete(rs)

    def send_task(self, client: int, task: ClientTask) -> None:
        self._track([self.comm.isend(task, dest=self.clients[client], tag=_TAG_TASK)], None)

    def recv_task(self) -> ClientTask:
        self._arrived(self.server, _TAG_TASK)
        return self.comm.recv(source=self.server, tag=_TAG_TASK)

    def send_image(self, payload: bytes) -> None:
        size = np.array([len(payload)], np.int64)
        body = np.frombuffer(payload, np.uint8)
        self._track([self.comm.Isend(size, dest=self.server, tag=_TAG_SIZE),
                     self.comm.Isend(body, dest=self.server, tag=_TAG_IMAGE)], (size, body, payload))

    def recv_image(self, client: int) -> np.ndarray:
        size = np.zeros(1, np.int64)
        self._arrived(self.clients[client], _TAG_SIZE)
        self.comm.Recv(size, source=self.clients[client], tag=_TAG_SIZE)
        buf = np.empty(int(size[0]), np.uint8)
        self._arrived(self.clients[client], _TAG_IMAGE)
        self.comm.Recv(buf, source=self.clients[client], tag=_TAG_IMAGE)
        return buf

    def fail(self, err: BaseException) -> None:
        say_rank_error(f"massview: error on rank 0 (dmmr server): {type(err).__name__}: {err}", self.comm.Get_size())
        self.comm.Abort(1)


class LocalLink:
    """The one-rank case: the server and its single client in one process."""

    def __init__(self):
        self.tasks: queue.Queue = queue.Queue()
        self.images: queue.Queue = queue.Queue()

    def send_task(self, client, task):
        self.tasks.put(task)

    def recv_task(self):
        item = self.tasks.get()
        if isinstance(item, BaseException):
            raise item
        return item

    def send_image(self, payload):
        self.images.put(payload)

    def recv_image(self, client):
        item = self.images.get()
        if isinstance(item, BaseException):
            raise item
        return np.frombuffer(item, np.uint8)

    def fail(self, err):
        self.images.put(err)
        self.tasks.put(err)

    def flush(self):
        pass
