"""Project exceptions.

Every error massview raises on purpose derives from :class:`MassviewError` and from the builtin
that fits it, so callers can catch either. Messages name the file, block or parameter at fault
and say what to do; the CLI prints the message (no traceback) and exits non-zero.
"""

from __future__ import annotations

__all__ = [
    "MassviewError",
    "ConfigError",
    "GLUnavailableError",
    "SceneNotFoundError",
    "ParallelError",
    "StoreError",
    "BlockNotFoundError",
    "CorruptBlockError",
    "IngestError",
    "OutputError",
    "RankJobError",
    "MassviewWarning",
    "describe",
    "disk_full",
    "full_disk_line",
]


class MassviewError(Exception):
    """Base class of all massview errors."""


class MassviewWarning(UserWarning):
    """Something given has no effect (an option the scene or system does not use); the work
    goes on. The CLI prints it as one ``massview: warning:`` line."""


class ConfigError(MassviewError, ValueError):
    """A parameter or option has a value massview cannot use."""


class GLUnavailableError(MassviewError, RuntimeError):
    """No headless OpenGL context could be created (EGL or a driver is missing)."""


class SceneNotFoundError(MassviewError, FileNotFoundError):
    """A scene or store name does not resolve to anything massview can render."""


class ParallelError(MassviewError, RuntimeError):
    """The MPI runtime could not start or a rank failed."""


class StoreError(MassviewError, OSError):
    """A store on disk is missing, incomplete or inconsistent; ``file``, where given, is the
    file at fault (so a caller can report a file once for the many records in it)."""

    def __init__(self, *args, file=None):
        super().__init__(*args)
        self.file = file


class BlockNotFoundError(StoreError, KeyError):
    """A block the store should hold is missing."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0]) if self.args else ""


class CorruptBlockError(StoreError):
    """A block exists but does not decode to what its metadata says."""


class IngestError(MassviewError, ValueError):
    """An input file cannot be read or has a shape/dtype massview cannot ingest."""


class OutputError(ConfigError, PermissionError):
    """An output folder or file cannot be created or written (checked before any work starts)."""


class RankJobError(ParallelError):
    """An MPI job started by ``massview.render(ranks=N)`` failed; the message is the failing
    rank's, ``returncode`` the job's exit status."""

    def __init__(self, message: str, returncode: int):
        super().__init__(message)
        self.returncode = returncode


def describe(e: BaseException) -> str:
    """``Type: message`` of an exception, or its type alone where the message is empty (a
    codec's ``MemoryError()``), for messages that name what failed."""
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


def disk_full(e: BaseException | None) -> str | None:
    """"no space left on the device" or "over the disk quota" where ``e``, or an exception it
    was raised from or while handling, is that OSError (ENOSPC, EDQUOT: a writer's cleanup often
    hits the full disk again, or a library wraps it); None otherwise."""
    import errno

    for x in _chain(e):
        if isinstance(x, OSError) and x.errno in (errno.ENOSPC, errno.EDQUOT):
            return "no space left on the device" if x.errno == errno.ENOSPC else "over the disk quota"
        text = str(x)  # (GDAL's errors through rasterio carry no errno, only its words)
        if "No space left on device" in text:
            return "no space left on the device"
        if "Disk quota exceeded" in text:
            return "over the disk quota"
    return None


def full_disk_line(e: BaseException, fallback) -> str:
    """One line for a write that ran out of room: what happened and where (the file the OSError
    names, else ``fallback``), without a traceback."""
    where = next((x.filename for x in _chain(e) if isinstance(x, OSError) and x.filename), None) or fallback
    return f"{disk_full(e)} writing {where}"


def _chain(e):
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        yield e
        e = e.__cause__ or e.__context__
