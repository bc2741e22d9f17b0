"""Run a benchmarked command in a child process and measure it: wall time, CPU time (user +
system, from ``RUSAGE_CHILDREN``: the child and everything it waited for, MPI ranks included)
and the child's own peak resident memory.

The peak is the child's ``VmHWM``, written at its exit to ``MASSVIEW_PEAK_RSS_FILE`` by the CLI
(``wait4``'s ``ru_maxrss`` would inherit the parent's high-water mark). For an MPI job the file
name holds ``{rank}``: every rank writes its own (``PMI_RANK``), the launcher ``launcher``.
"""

from __future__ import annotations

import os
import resource
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["ChildRun", "run_measured"]


@dataclass(frozen=True)
class ChildRun:
    returncode: int
    wall_s: float
    cpu_s: float
    peak_rss: int  # bytes; 0 when the child failed before writing it
    rank_peak_rss: dict = field(default_factory=dict)  # {rank: bytes} of an MPI job (ranks=N)


def run_measured(cmd: list[str], rss_file: Path, ranks: int = 0) -> ChildRun:
    """Run ``cmd`` (a ``python -m massview ...`` command line) and measure it; with ``ranks``
    > 0 also read the peak RSS of each of its MPI ranks."""
    per_rank = ranks > 0
    target = rss_file.with_name(rss_file.name + ".{rank}") if per_rank else rss_file
    for p in rss_file.parent.glob(rss_file.name + "*"):
        p.unlink()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=dict(os.environ, MASSVIEW_PEAK_RSS_FILE=str(target)))
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)

    def read(p: Path) -> int:
        return int(p.read_text()) if proc.returncode == 0 and p.exists() else 0

    if not per_rank:
        return ChildRun(proc.returncode, wall, cpu, read(rss_file))
    ranks_rss = {r: read(Path(str(target).replace("{rank}", str(r)))) for r in range(ranks)}
    return ChildRun(proc.returncode, wall, cpu, read(Path(str(target).replace("{rank}", "launcher"))), ranks_rss)
