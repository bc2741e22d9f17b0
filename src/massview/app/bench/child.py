"""Run a benchmarked command in a child process and measure it: wall time, CPU time (user +
system, from ``RUSAGE_CHILDREN``) and the child's own peak resident memory.

The peak is the child's ``VmHWM``, written at its exit to ``MASSVIEW_PEAK_RSS_FILE`` by the CLI
(``wait4``'s ``ru_maxrss`` would inherit the parent's high-water mark).
"""

from __future__ import annotations

import os
import resource
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ChildRun", "run_measured"]


@dataclass(frozen=True)
class ChildRun:
    returncode: int
    wall_s: float
    cpu_s: float
    peak_rss: int  # bytes; 0 when the child failed before writing it


def run_measured(cmd: list[str], rss_file: Path) -> ChildRun:
    """Run ``cmd`` (a ``python -m massview ...`` command line) and measure it."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=dict(os.environ, MASSVIEW_PEAK_RSS_FILE=str(rss_file)))
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    rss = int(rss_file.read_text()) if proc.returncode == 0 and rss_file.exists() else 0
    return ChildRun(proc.returncode, wall, cpu, rss)
