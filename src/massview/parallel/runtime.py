"""The MPI runtime: launching ranks, the world communicator, and failing fast.

``massview`` commands that take ``--ranks N`` run in one of two ways:

* **inside an MPI job** (started by ``mpiexec``/``srun``, detected from the process-manager
  environment): every rank runs the command and uses all the ranks it was given;
* **standalone**: with N > 1 the command re-executes itself as
  ``mpiexec -n N python -m massview ...`` with the ``mpiexec`` installed beside the Python
  interpreter (the ``mpich`` wheel's) or on PATH, and returns its exit status; stop signals
  sent to the launching process are forwarded to the job (:mod:`.launcher`).

``guarded(comm, fn)`` runs a rank's work; an exception on any rank prints that rank's error
once and calls ``MPI_Abort`` so that every rank ends and ``mpiexec`` exits non-zero — a
failing rank never leaves the others waiting in a collective. In a job started by
:func:`relaunch` the rank writes its error line to a file instead (:data:`ERRORS_ENV`), and the
launching process prints it once the job has ended: hydra's ``MPI_Abort`` teardown can end the
job before its proxy has forwarded what the rank wrote to stderr (a CI run lost both the rank's
line and MPICH's own "Abort(1)" line).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import traceback
from pathlib import Path

from ..core.errors import MassviewError, ParallelError, disk_full, full_disk_line
from .launcher import run_job

__all__ = ["in_mpi_job", "find_mpiexec", "relaunch", "world", "self_comm", "guarded", "say_rank_error", "reuse_freed_memory", "return_free_heap", "raster_threads", "launch_env", "local_cores", "interrupt_on_sigterm", "ignore_late_sigterm"]

ERRORS_ENV = "MASSVIEW_RANK_ERRORS"  # the file a rank of a relaunched job writes its error line to
_JOB_VARS = ("PMI_RANK", "PMI_SIZE", "PMIX_RANK", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS", "HYDRA_CONTROL_FD", "MASSVIEW_UNDER_MPI")


def in_mpi_job() -> bool:
    """True when this process was started by an MPI process manager."""
    return any(v in os.environ for v in _JOB_VARS)


def find_mpiexec() -> str:
    here = Path(sys.executable).parent / "mpiexec"
    if here.exists():
        return str(here)
    found = shutil.which("mpiexec") or shutil.which("mpirun")
    if not found:
        raise ParallelError(
            "no mpiexec found: install the mpich wheel (`pip install mpich`, part of massview's "
            "dependencies) or load your cluster's MPI module, or run under an external mpiexec"
        )
    return found


def relaunch(argv: list[str], nranks: int) -> int:
    """Run ``python -m massview argv...`` on ``nranks`` local ranks; returns the exit status.
    SIGINT, SIGTERM and SIGHUP sent to this process stop the job (see :mod:`.launcher`): the
    ranks get the signal, a job still running after a grace period is killed, and the signal
    then reaches the caller (KeyboardInterrupt for SIGINT, ``SystemExit(143)`` for SIGTERM)
    unless the job stopped cleanly on it (status 0, as the viewer does)."""
    cmd = [find_mpiexec(), "-n", str(nranks), sys.executable, "-m", "massview", *argv]
    env = dict(os.environ, MASSVIEW_UNDER_MPI="1")
    try:
        fd, errors = tempfile.mkstemp(prefix="massview-errors-", suffix=".txt")
        os.close(fd)
        env[ERRORS_ENV] = errors
    except OSError:  # no writable temporary folder: the ranks print their lines themselves
        errors = None
    try:
        return run_job(cmd, launch_env(nranks, env))
    finally:
        if errors is not None:
            _relay_errors(errors)


def _relay_errors(path: str) -> None:
    """Print what the job's ranks wrote to ``path`` (their error lines) and remove it."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read()
        os.unlink(path)
    except OSError:
        return
    if text:
        sys.stderr.write(text if text.endswith("\n") else text + "\n")
        sys.stderr.flush()


def say_rank_error(msg: str, size: int) -> None:
    """A rank's error line: to the launcher's file (:data:`ERRORS_ENV`) in a job of several
    ranks that :func:`relaunch` started, else (or where that file cannot be written) to stderr."""
    path = os.environ.get(ERRORS_ENV)
    if size > 1 and path:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_APPEND)
            try:
                os.write(fd, (msg + "\n").encode("utf-8", "replace"))  # one write: lines of several ranks never mix
            finally:
                os.close(fd)
            return
        except OSError:
            pass
    print(msg, file=sys.stderr, flush=True)


def interrupt_on_sigterm() -> None:
    """In a rank: SIGTERM (what ``mpiexec`` forwards when its launcher is told to stop, and what
    a batch system sends first) raises KeyboardInterrupt as SIGINT does, so the rank ends through
    :func:`guarded` (one "interrupted" line, every rank aborted) instead of dying mid-frame and
    leaving ``mpiexec``'s "BAD TERMINATION" banner. Left alone where SIGTERM is not at its default
    (a command that handles it itself, as the viewer does, installs its handler later)."""
    import signal

    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, signal.default_int_handler)


def ignore_late_sigterm() -> None:
    """In a rank whose work is done (its command returned): SIGTERM is ignored from now on, so a
    stop that reaches the ranks while they finish (Ctrl-C just after the last frame) lets the
    job end as the success it is, instead of interrupting ranks in ``MPI_Finalize``, which
    MPICH reported under its "BAD TERMINATION" banner (walk7 L1). Only where
    :func:`interrupt_on_sigterm` installed its handler."""
    import signal

    try:
        if signal.getsignal(signal.SIGTERM) is signal.default_int_handler:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
    except ValueError:  # (not the main thread)
        pass


def world():
    """MPI.COMM_WORLD (initializes MPI on first use; a singleton job when not under mpiexec)."""
    from mpi4py import MPI

    return MPI.COMM_WORLD


def guarded(comm, fn, *args, **kw):
    """Run ``fn`` on this rank; on an exception print it once, prefixed by the rank, and abort
    every rank with exit status 1 (a single-rank run exits the same way, without MPI_Abort).
    In a job :func:`relaunch` started, the line goes to the launcher, which prints it after the
    job (:func:`say_rank_error`).

    An interruption (KeyboardInterrupt: SIGINT, or SIGTERM through :func:`interrupt_on_sigterm`)
    of a job that massview launched itself (:func:`relaunch`) aborts with status 130 quietly:
    no line from the rank and none from MPICH's ``MPI_Abort`` (this rank's stderr is closed just
    before it), since the launching process, which stopped the job, says it once. Any other
    exception, and an interruption under an external ``mpiexec``, prints as above."""
    try:
        return fn(*args, **kw)
    except BaseException as e:  # noqa: BLE001 - any failure must end every rank
        rank, size = comm.Get_rank(), comm.Get_size()
        interrupted = isinstance(e, KeyboardInterrupt)
        quiet = interrupted and size > 1 and os.environ.get("MASSVIEW_UNDER_MPI") == "1"
        prefix = f"massview: error on rank {rank} of {size}: " if size > 1 else "massview: error: "
        if isinstance(e, MassviewError):
            msg = prefix + str(e)
        elif disk_full(e):  # one line, as for the single-rank run (walk9 M1)
            msg = prefix + full_disk_line(e, "the output") + "; free space (or choose another output) and run the command again"
        elif interrupted:
            msg = prefix + "interrupted"
        else:
            msg = prefix + f"{type(e).__name__}: {e}\n" + "".join(traceback.format_exception(e))
        if not quiet:
            say_rank_error(msg, size)
        if size > 1:
            if quiet:
                _close_stderr()
            comm.Abort(130 if interrupted else 1)
        raise SystemExit(130 if interrupted else 1) from None


def _close_stderr() -> None:
    """Point file descriptor 2 at /dev/null (what this process writes is flushed first)."""
    try:
        sys.stderr.flush()
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, 2)
        os.close(fd)
    except OSError:
        pass


def self_comm():
    """MPI.COMM_SELF: a one-rank communicator for serial tools and benchmarks."""
    from mpi4py import MPI

    return MPI.COMM_SELF


def reuse_freed_memory(mmap_max: int = 32 << 20, keep: int = 64 << 20) -> bool:
    """Let glibc serve per-frame buffers (images, messages, readbacks: 1–32 MiB) from memory
    freed by the previous frame instead of fresh pages from the kernel: a fresh 1280×1024
    RGBA + depth image costs ~5 ms of page faults here, more than compositing it. Sets
    M_MMAP_THRESHOLD to ``mmap_max`` (larger blocks are still mapped and unmapped) and keeps up
    to ``keep`` bytes of freed heap (M_TRIM_THRESHOLD). Process-wide, so the app calls it once
    at start-up; a no-op (False) where the C library is not glibc."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h>
    return bool(mallopt(m_mmap_threshold, mmap_max)) and bool(mallopt(m_trim_threshold, keep))


def return_free_heap() -> bool:
    """Give the free pages of every malloc arena back to the kernel (glibc ``malloc_trim(0)``).
    With :func:`reuse_freed_memory`'s settings glibc keeps freed blocks below 32 MiB for reuse,
    so a one-off burst of temporaries (a terrain system's open: ~130 MiB at 32769²) would stay
    resident for the whole run; systems call this once after such a burst, never per frame. A
    no-op (False) where the C library is not glibc."""
    import ctypes
    import ctypes.util

    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return False
    return bool(trim(0))


def raster_threads(ranks_here: int, cores: int | None = None) -> int | None:
    """LP_NUM_THREADS for llvmpipe when ``ranks_here`` ranks share this machine's ``cores``:
    None (Mesa's own default, one raster thread per core in every rank) while the ranks do not
    outnumber the cores, else 0 (every rank rasterizes on its main thread, no hand-off).
    Decided by ``massview bench frame --lp-threads auto,default,1`` (issue 20, README): at 2
    ranks on 2 cores Mesa's default was faster in both runs, at 4 ranks 0 was (0.60–0.82× the
    frame time); on a loaded machine more threads also win a larger share of the CPU."""
    if cores is None:
        cores = local_cores()
    return None if ranks_here <= cores else 0


# How waiting ranks give their core back when local ranks outnumber the cores: massview's own
# sleeping wait (parallel/exchange.py, ``MASSVIEW_MPI_WAIT=sleep``) instead of MPICH's
# busy-polling blocking calls. Measured with ``massview bench composite --wait poll,sleep``
# (both modes in one job, alternating; README "How local ranks share the cores"): sleep took
# 0.86x poll's time at 3 and at 4 ranks on 2 cores, 1.04-1.08x at 2 ranks (so not there).
# MPICH's own throttle (MPIR_CVAR_CH4_PROGRESS_THROTTLE*, set here before) is not a CVAR of
# the mpich 5.0.2 wheel: it did nothing.
WAIT_ENV = {"MASSVIEW_MPI_WAIT": "sleep"}


def local_cores() -> int:
    """The CPUs this process may run on (its affinity; elsewhere the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def launch_env(nranks: int, env: dict[str, str], cores: int | None = None) -> dict[str, str]:
    """``env`` with the launcher's defaults for ``nranks`` local ranks on ``cores`` (default:
    this machine's) added where the user set nothing: when the ranks outnumber the cores,
    waiting ranks sleep (:data:`WAIT_ENV`), and llvmpipe gets :func:`raster_threads` raster
    threads per rank (``LP_NUM_THREADS``, when it says so). Variables already in ``env`` win,
    so either can be set by hand."""
    out = dict(env)
    cores = local_cores() if cores is None else cores
    if nranks > cores:
        for key, value in WAIT_ENV.items():
            out.setdefault(key, value)
    threads = raster_threads(nranks, cores)
    if threads is not None:
        out.setdefault("LP_NUM_THREADS", str(threads))
    return out
