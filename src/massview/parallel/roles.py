"""Roles: ranks with different jobs in one run (T2, M1, M2; T1 is the one-role case).

A system declares its roles in order, each with a rank count (or ``None`` for "all the ranks
the others leave", at most one role)::

    roles = (Role("visualization", None, minimum=1), Role("computation", 4))
    rc = split_roles(comm, roles)          # collective over comm
    rc.role                                # this rank's role name
    rc.comm                                # the sub-communicator of this rank's role
    rc.ranks["computation"]                # parent-comm ranks of a role, in role-rank order
    rc.parent                              # the given comm: the inter-role communicator
    run_roles(rc, {"visualization": vis_loop, "computation": comp_loop}, *args)

Ranks are given to roles in declaration order and in parent-rank order: the first role gets
parent ranks 0 .. k-1, and so on, so the first role's rank 0 is the parent's rank 0 (for T2,
the visualization leader that writes the frames and the stats). ``split_roles`` is one
``Comm.Split`` (colour = role index, key = parent rank); every rank computes the same rank map
from the declaration and the parent size, so no other message is needed. Messages between
roles go over ``parent`` addressed by the rank map; messages inside a role over ``comm``.
Library code receives these communicators — never ``COMM_WORLD``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..core.errors import ConfigError

__all__ = ["Role", "RoleComms", "assign_roles", "split_roles", "run_roles", "send_bytes", "recv_bytes", "wait_all"]


@dataclass(frozen=True)
class Role:
    """A job ranks can have: ``count`` ranks (None = the rest), at least ``minimum``."""

    name: str
    count: int | None = None
    minimum: int = 1

    def __post_init__(self) -> None:
        if self.count is not None and self.count < self.minimum:
            raise ConfigError(f"role {self.name!r}: {self.count} ranks given, at least {self.minimum} needed")


def assign_roles(roles: Sequence[Role], size: int) -> dict[str, list[int]]:
    """Parent ranks of each role for a communicator of ``size`` ranks (pure; raises
    ConfigError naming what to change when the ranks do not suffice)."""
    names = [r.name for r in roles]
    if len(set(names)) != len(names):
        raise ConfigError(f"duplicate role names in {names}")
    rest = [r for r in roles if r.count is None]
    if len(rest) > 1:
        raise ConfigError(f"only one role may take the remaining ranks, got {[r.name for r in rest]}")
    fixed = sum(r.count for r in roles if r.count is not None)
    left = size - fixed
    need = fixed + sum(r.minimum for r in rest)
    if left < 0 or need > size or (not rest and left != 0):
        desc = ", ".join(f"{r.name}: {r.count if r.count is not None else f'the rest (≥ {r.minimum})'}" for r in roles)
        raise ConfigError(f"roles ({desc}) need {need}{'' if rest else ' exactly'} ranks, the run has {size}; "
                          f"change --ranks or the role counts")
    out, start = {}, 0
    for r in roles:
        k = r.count if r.count is not None else left
        out[r.name] = list(range(start, start + k))
        start += k
    return out


@dataclass
class RoleComms:
    """This rank's view of the roles: its role, the role's sub-communicator, the parent
    (inter-role) communicator and every role's parent ranks."""

    role: str
    comm: Any
    parent: Any
    ranks: dict[str, list[int]] = field(default_factory=dict)

    @property
    def role_rank(self) -> int:
        return self.comm.Get_rank()

    def leader(self, role: str) -> int:
        """Parent rank of ``role``'s rank 0."""
        return self.ranks[role][0]

    def role_of(self, parent_rank: int) -> str:
        return next(name for name, rs in self.ranks.items() if parent_rank in rs)


def split_roles(comm, roles: Sequence[Role]) -> RoleComms:
    """Split ``comm`` into one sub-communicator per role (collective over ``comm``)."""
    ranks = assign_roles(roles, comm.Get_size())
    me = comm.Get_rank()
    index = next(i for i, r in enumerate(roles) if me in ranks[r.name])
    sub = comm.Split(index, me)
    return RoleComms(roles[index].name, sub, comm, ranks)


def run_roles(rc: RoleComms, loops: Mapping[str, Callable[..., Any]], *args, **kw) -> Any:
    """Run this rank's per-role loop ``loops[rc.role](rc, *args, **kw)`` and return its result."""
    if rc.role not in loops:
        raise ConfigError(f"no loop for role {rc.role!r} (have {sorted(loops)})")
    return loops[rc.role](rc, *args, **kw)


# -- byte messages between roles ------------------------------------------------------------------
def send_bytes(comm, payloads: Mapping[int, np.ndarray], tag: int = 0) -> list:
    """Start non-blocking sends of uint8 buffers to ``dest -> buffer``; returns the requests
    (wait on them with :func:`wait_all`)."""
    return [comm.Isend([np.ascontiguousarray(buf, np.uint8), _mpi().BYTE], dest=d, tag=tag) for d, buf in payloads.items()]


def recv_bytes(comm, sources: Sequence[int], tag: int = 0) -> dict[int, np.ndarray]:
    """Receive one uint8 buffer from each of ``sources`` (any arrival order)."""
    MPI = _mpi()
    out: dict[int, np.ndarray] = {}
    status = MPI.Status()
    pending = set(sources)
    while pending:
        comm.Probe(source=MPI.ANY_SOURCE, tag=tag, status=status)
        src = status.Get_source()
        if src not in pending:
            raise ConfigError(f"unexpected message from rank {src} (tag {tag})")
        buf = np.empty(status.Get_count(MPI.BYTE), np.uint8)
        comm.Recv([buf, MPI.BYTE], source=src, tag=tag)
        out[src] = buf
        pending.discard(src)
    return out


def wait_all(requests: list) -> None:
    if requests:
        _mpi().Request.Waitall(requests)


def _mpi():
    from mpi4py import MPI

    return MPI
