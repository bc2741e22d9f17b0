"""Per-frame process counters of the massive-model system (M1, §4's speed-up experiment).

:class:`ProcessMeter` samples the whole process between two delivered frames: CPU seconds
(user + system, every thread: ``resource.getrusage``), bytes read through the file system
(``rchar`` of ``/proc/self/io``: page-cache hits included) and bytes the block device really
delivered (``read_bytes``). On a system without ``/proc/self/io`` the byte counters stay 0.
:func:`drop_page_cache` asks the kernel to forget a store's cached pages
(``posix_fadvise(DONTNEED)``), so a cold run really reads from the device.
"""

from __future__ import annotations

import os
import resource
from pathlib import Path

__all__ = ["ProcessMeter", "io_counters", "drop_page_cache"]


def io_counters() -> tuple[int, int]:
    """(bytes read through the file system, bytes read from the block device) so far, this process."""
    try:
        text = Path("/proc/self/io").read_text()
    except OSError:
        return 0, 0
    vals = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    return int(vals.get("rchar", 0)), int(vals.get("read_bytes", 0))


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


class ProcessMeter:
    """``step()``: the counters since the previous ``step()`` (or construction) as a dict of
    ``cpu_ms``, ``file_read_bytes``, ``device_read_bytes``."""

    def __init__(self):
        self._last = self._sample()

    @staticmethod
    def _sample() -> tuple[float, int, int]:
        return (_cpu_s(), *io_counters())

    def step(self) -> dict:
        now = self._sample()
        last, self._last = self._last, now
        return {"cpu_ms": round((now[0] - last[0]) * 1e3, 3), "file_read_bytes": now[1] - last[1],
                "device_read_bytes": now[2] - last[2]}


def drop_page_cache(root: str | os.PathLike) -> int:
    """``posix_fadvise(POSIX_FADV_DONTNEED)`` on every file under ``root`` (a store directory or
    file), after writing back its dirty pages (``fdatasync``: the kernel keeps dirty pages);
    returns the bytes advised."""
    root = Path(root)
    files = [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file()]
    total = 0
    for p in files:
        fd = os.open(p, os.O_RDONLY)
        try:
            size = os.fstat(fd).st_size
            try:
                os.fdatasync(fd)  # dirty pages are not dropped: write them back first
            except OSError:
                pass
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            total += size
        finally:
            os.close(fd)
    return total
