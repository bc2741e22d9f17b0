"""Running a local ``mpiexec`` job as a child and stopping it when this process is told to stop.

``mpiexec`` is started in a session of its own, so a terminal's Ctrl-C reaches this process
only, and this process stands for the whole job: SIGINT, SIGTERM and SIGHUP sent to it (by a
terminal, ``kill``, ``timeout``, systemd, a notebook's ``send_signal``) are forwarded to
``mpiexec`` as SIGTERM. MPICH's hydra ``mpiexec`` (the ``mpich`` wheel's) forwards SIGTERM to
every rank (its proxies and ranks each run in a session of their own, so signalling a process
group would reach ``mpiexec`` alone), where it raises KeyboardInterrupt as SIGINT does
(:func:`massview.parallel.runtime.interrupt_on_sigterm`; the viewer handles both alike); a
forwarded SIGINT would make hydra print two lines of its own ("Sending Ctrl-C to processes as
requested", "Press Ctrl-C again to force abort") under the one this process prints. A second
signal kills the job at once, and a job still running ``grace`` seconds after the first is
killed: ``mpiexec`` and every process below it (SIGKILL).

Once the job has ended, a signal is handed on to the caller as if the job had not been there:
the handler that was installed before is called (Python's default SIGINT handler raises
KeyboardInterrupt), or, where that was the default action, ``SystemExit(128 + signal)``
(143 for SIGTERM) is raised, so ``finally`` blocks still run. A job that stopped cleanly on the
signal (status 0: the viewer's Ctrl-C ends it normally) is not an interruption: its 0 is
returned. Handlers are installed only from the main thread (Python allows no other), and a
signal set to be ignored (``nohup``) stays ignored.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

__all__ = ["run_job", "STOP_GRACE_S", "descendants"]

STOP_GRACE_S = 30.0  # the viewer stops at the next frame, a render at once; a loaded machine can take several seconds
_STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (children, their children, ...), read from /proc;
    [] where there is no /proc."""
    children: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    for name in entries:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                stat = f.read()
        except OSError:
            continue
        ppid = int(stat[stat.rindex(b")") + 2:].split()[1])  # after "(comm) state"
        children.setdefault(ppid, []).append(int(name))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def _send(proc: subprocess.Popen, signum: int) -> None:
    if proc.returncode is None:
        try:
            os.kill(proc.pid, signum)
        except ProcessLookupError:
            pass


def _kill_tree(proc: subprocess.Popen) -> None:
    """SIGKILL ``proc`` and everything below it (ranks first, so none outlives its proxy)."""
    for pid in reversed(descendants(proc.pid)):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    _send(proc, signal.SIGKILL)


def _install(handler) -> dict:
    """Install ``handler`` for the stop signals; returns {signal: previous handler}."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    previous = {}
    for s in _STOP_SIGNALS:
        old = signal.getsignal(s)
        if old is signal.SIG_IGN or old is None:  # ignored (nohup), or set outside Python: leave it
            continue
        previous[s] = old
        signal.signal(s, handler)
    return previous


def _hand_on(signum: int, previous: dict, rc: int) -> int:
    """Deliver ``signum`` to this process's own earlier handler, now that the job is over."""
    old = previous.get(signum, signal.SIG_DFL)
    if callable(old):
        old(signum, None)  # default_int_handler raises KeyboardInterrupt
        return rc
    raise SystemExit(128 + signum)


def run_job(cmd: list[str], env: dict[str, str], grace: float = STOP_GRACE_S) -> int:
    """Run ``cmd`` (an ``mpiexec`` command line) to its end and return its exit status,
    stopping it as the module docstring says when this process gets a stop signal."""
    proc = subprocess.Popen(cmd, env=env, start_new_session=True)
    got: list[int] = []

    def forward(signum, frame):
        got.append(signum)
        _send(proc, signal.SIGTERM)

    previous = _install(forward)
    try:
        deadline = None
        while True:
            try:
                rc = proc.wait(timeout=0.25)
                break
            except subprocess.TimeoutExpired:
                pass
            if got and deadline is None:
                deadline = time.monotonic() + grace
            twice = len(got) > 1
            if deadline is not None and deadline != float("inf") and (twice or time.monotonic() > deadline):
                why = "asked to stop twice" if twice else f"the job did not stop within {grace:g} s of {signal.Signals(got[0]).name}"
                print(f"massview: {why}; killing it", file=sys.stderr, flush=True)
                _kill_tree(proc)
                deadline = float("inf")
    except BaseException:  # KeyboardInterrupt where no handler could be installed, or anything else: no job left behind
        _send(proc, signal.SIGTERM)
        try:
            proc.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            _kill_tree(proc)
            proc.wait()
        raise
    finally:
        for s, old in previous.items():
            signal.signal(s, old)
    if got and rc != 0:
        return _hand_on(got[0], previous, rc)
    return rc
