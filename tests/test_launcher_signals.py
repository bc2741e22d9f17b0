"""Stopping a ``--ranks N`` job by signalling the launching process alone (``kill``, ``timeout``,
systemd, a notebook's ``send_signal``), not its process group as a terminal's Ctrl-C does:
the launcher exits with the conventional status and no process of the job is left. Real
processes under the real ``mpiexec``; the job's processes are read from /proc."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import SMALL_SCENE, clean_env

pytestmark = [pytest.mark.mpi, pytest.mark.slow,
              pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the job's processes from /proc")]


def _stat(pid: int) -> tuple[int, str, int] | None:
    """(ppid, state, start time) of a process, or None when there is none."""
    try:
        raw = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return None
    fields = raw[raw.rindex(b")") + 2:].split()
    return int(fields[1]), fields[0].decode(), int(fields[19])


def _job_tree(pid: int) -> dict[int, int]:
    """{pid: start time} of every process below ``pid``."""
    procs = {int(p): _stat(int(p)) for p in os.listdir("/proc") if p.isdigit()}
    out, todo = {}, [pid]
    while todo:
        parent = todo.pop()
        for p, st in procs.items():
            if st is not None and st[0] == parent and p not in out:
                out[p] = st[2]
                todo.append(p)
    return out


def _alive(tree: dict[int, int]) -> list[str]:
    """The processes of ``tree`` still running (same pid and start time, not a zombie)."""
    left = []
    for pid, start in tree.items():
        st = _stat(pid)
        if st is not None and st[2] == start and st[1] != "Z":
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            left.append(f"{pid}: {cmd}")
    return left


def _kill_all(proc: subprocess.Popen, tree: dict[int, int]) -> None:
    """Clean-up after a failed test: SIGKILL whatever of the job is left."""
    for pid, start in [*tree.items(), (proc.pid, None)]:
        st = _stat(pid)
        if st is not None and (start is None or st[2] == start):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    proc.wait(timeout=30)


def _start(args: list[str], log: Path) -> subprocess.Popen:
    with open(log, "w") as f:  # a file, not a pipe: nobody has to read it while the job runs
        return subprocess.Popen([sys.executable, "-m", "massview", *args], stdout=f, stderr=subprocess.STDOUT,
                                env=clean_env(), start_new_session=True)


def _wait_for(cond, proc: subprocess.Popen, log: Path, what: str, limit: float = 240) -> None:
    t0 = time.monotonic()
    while not cond():
        assert proc.poll() is None, f"the job ended before {what} (status {proc.returncode}):\n{log.read_text()[-3000:]}"
        assert time.monotonic() - t0 < limit, f"no {what} after {limit} s:\n{log.read_text()[-3000:]}"
        time.sleep(0.2)


def _stop_and_check(proc: subprocess.Popen, tree: dict[int, int], signum: int, log: Path) -> int:
    """Send ``signum`` to the launcher only; returns its exit status once it and the whole job
    have gone (generous limits: this checks that they stop, not how fast)."""
    os.kill(proc.pid, signum)
    try:
        rc = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the launcher still runs 60 s after {signal.Signals(signum).name}:\n{log.read_text()[-3000:]}")
    t0 = time.monotonic()
    while _alive(tree) and time.monotonic() - t0 < 30:
        time.sleep(0.2)
    assert not _alive(tree), f"left running after {signal.Signals(signum).name}: {_alive(tree)}\n{log.read_text()[-3000:]}"
    return rc


@pytest.mark.parametrize("signum, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["SIGTERM", "SIGINT"])
def test_a_signal_to_the_render_launcher_stops_the_whole_job(tmp_path, signum, status):
    out = tmp_path / f"out-{signum}"
    log = tmp_path / "log.txt"
    proc = _start(["render", "builtin:objects", "--ranks", "2", "--frames", "500", "--size", "320x240", "--out", str(out)], log)
    tree: dict[int, int] = {}
    try:
        _wait_for(lambda: (out / "stats.jsonl").exists() and (out / "stats.jsonl").stat().st_size > 0, proc, log, "frame written")
        tree = _job_tree(proc.pid)
        assert len(tree) >= 3, f"expected mpiexec and two ranks below the launcher, found {tree}"
        rc = _stop_and_check(proc, tree, signum, log)
        text = log.read_text()
        assert rc == status, f"exit status {rc}, not {status}:\n{text[-3000:]}"
        assert "Traceback" not in text, text[-3000:]
        # one line, from the launcher (it said "error on rank R of 2: interrupted" per rank, MPICH's
        # "Abort(130) on node ..." and, for SIGINT, hydra's "Sending Ctrl-C to processes as requested")
        said = re.findall(r"massview: interrupted after (\d+) frames?; frames so far in (\S+)", text)
        assert len(said) == 1 and said[0][1] == str(out), text[-3000:]
        assert int(said[0][0]) == len({json.loads(line)["frame"] for line in (out / "stats.jsonl").read_text().splitlines()})
        pngs = len(list((out / "frames").glob("*.png")))  # walk7 L2: an image written before its record is counted apart
        assert (f"({pngs} images in frames/, the last without its stats record)" in text) == (pngs > int(said[0][0])), text[-3000:]
        assert "error on rank" not in text and "Abort(" not in text and "[mpiexec@" not in text, text[-3000:]
    finally:
        if proc.poll() is None or _alive(tree):
            _kill_all(proc, tree)


def test_an_interrupted_dmmr_render_keeps_its_frames_statistics(tmp_path):
    """walk6 #7: M1's statistics came only at the end, so Ctrl-C said "interrupted after 0
    frames" with 76 frames written and an empty stats.jsonl. The server's record of each
    frame is written as it is finished."""
    out, log = tmp_path / "out", tmp_path / "log.txt"
    proc = _start(["render", "builtin:objects", "--system", "dmmr", "--ranks", "3", "--frames", "500", "--size", "320x240",
                   "--out", str(out)], log)
    tree: dict[int, int] = {}
    try:
        _wait_for(lambda: (out / "stats.jsonl").exists() and (out / "stats.jsonl").stat().st_size > 0, proc, log, "frame recorded")
        tree = _job_tree(proc.pid)
        rc = _stop_and_check(proc, tree, signal.SIGINT, log)
        text = log.read_text()
        assert rc == 130 and "Traceback" not in text, text[-3000:]
        said = re.findall(r"massview: interrupted after (\d+) frames?; frames so far in (\S+)", text)
        frames = {json.loads(line)["frame"] for line in (out / "stats.jsonl").read_text().splitlines()}
        assert len(said) == 1 and int(said[0][0]) == len(frames) > 0, text[-3000:]
        assert len(list((out / "frames").glob("*.png"))) >= len(frames)
    finally:
        if proc.poll() is None or _alive(tree):
            _kill_all(proc, tree)


def test_sigterm_to_the_view_launcher_frees_the_port_and_leaves_no_ranks(tmp_path):
    """Also: ``--port 0`` (which the port-in-use message suggests) picks a free port and serves."""
    log = tmp_path / "log.txt"
    proc = _start(["view", SMALL_SCENE, "--ranks", "2", "--port", "0", "--size", "320x240"], log)
    tree: dict[int, int] = {}
    try:
        _wait_for(lambda: "serving http" in log.read_text(), proc, log, "'serving' line")
        port = int(re.search(r"serving http://127\.0\.0\.1:(\d+)/", log.read_text()).group(1))
        assert port > 0
        with socket.create_connection(("127.0.0.1", port), timeout=10):
            pass  # it serves there
        tree = _job_tree(proc.pid)
        assert len(tree) >= 3, f"expected mpiexec and two ranks below the launcher, found {tree}"
        rc = _stop_and_check(proc, tree, signal.SIGTERM, log)
        text = log.read_text()
        assert rc == 0, f"the viewer stops cleanly on SIGTERM, got status {rc}:\n{text[-3000:]}"
        assert "viewer stopped after" in text, text[-3000:]
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))  # the port is free again
    finally:
        if proc.poll() is None or _alive(tree):
            _kill_all(proc, tree)


_API_CALLER = """
import sys
from massview import api
try:
    api.render("builtin:objects", ranks=2, frames=500, size="320x240", out=sys.argv[1], images=False)
except KeyboardInterrupt:
    print("caught KeyboardInterrupt", flush=True)
    sys.exit(5)
print("render finished", flush=True)
"""


def test_keyboardinterrupt_in_an_api_caller_stops_its_rank_job(tmp_path):
    """``massview.api.render(ranks=2)`` in a process that gets SIGINT (a notebook's interrupt):
    the caller sees KeyboardInterrupt once the job is gone, and the job's folder is removed."""
    out, log, tmp = tmp_path / "out", tmp_path / "log.txt", tmp_path / "tmp"
    tmp.mkdir()
    with open(log, "w") as f:
        proc = subprocess.Popen([sys.executable, "-c", _API_CALLER, str(out)], stdout=f, stderr=subprocess.STDOUT,
                                env=clean_env(TMPDIR=str(tmp)), start_new_session=True)
    tree: dict[int, int] = {}
    try:
        _wait_for(lambda: (out / "stats.jsonl").exists(), proc, log, "frame written")
        tree = _job_tree(proc.pid)
        assert len(tree) >= 3, f"expected mpiexec and two ranks below the caller, found {tree}"
        rc = _stop_and_check(proc, tree, signal.SIGINT, log)
        assert rc == 5 and "caught KeyboardInterrupt" in log.read_text(), log.read_text()[-3000:]
        assert not list(tmp.glob("massview-job-*")), "the job's temporary folder is left behind"
    finally:
        if proc.poll() is None or _alive(tree):
            _kill_all(proc, tree)


_STUBBORN = """
import os, sys
from massview.parallel.launcher import run_job
from massview.parallel.runtime import find_mpiexec
rank = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(600)"
run_job([find_mpiexec(), "-n", "2", sys.executable, "-c", rank], dict(os.environ), grace=3)
"""


def test_a_job_that_ignores_the_signal_is_killed_after_the_grace_period(tmp_path):
    log = tmp_path / "log.txt"
    with open(log, "w") as f:
        proc = subprocess.Popen([sys.executable, "-c", _STUBBORN], stdout=f, stderr=subprocess.STDOUT, env=clean_env(),
                                start_new_session=True)
    tree: dict[int, int] = {}
    try:
        _wait_for(lambda: log.read_text().count("up") == 2, proc, log, "ranks up", limit=120)
        tree = _job_tree(proc.pid)
        assert len(tree) >= 3, tree
        assert _stop_and_check(proc, tree, signal.SIGTERM, log) == 143
        assert "did not stop within 3 s of SIGTERM; killing it" in log.read_text()
    finally:
        if proc.poll() is None or _alive(tree):
            _kill_all(proc, tree)


def test_a_rank_whose_command_returned_ignores_a_late_sigterm(terrain_store):
    """walk7 L1: a Ctrl-C just after the last frame reached the ranks as SIGTERM while they
    finished (MPI_Finalize): MPICH printed its "BAD TERMINATION" banner and the launcher said
    "interrupted" for a run that had completed. A rank ignores SIGTERM once its command has
    returned; before that it is an interruption (interrupt_on_sigterm), as the tests above show."""
    code = ("import os, signal, sys, time\n"
            "from massview.app.cli import main\n"
            f"rc = main(['info', {str(terrain_store)!r}])\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "time.sleep(0.3)\n"
            "print('finished', rc)\n")
    env = {**clean_env(), "PMI_RANK": "0"}  # (what marks a process as a rank: massview.parallel.runtime.in_mpi_job)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "finished 0" in proc.stdout, proc.stderr[-2000:]
