"""A failing rank's error line reaches the user even where MPI_Abort's teardown loses the rank's
stderr: in a job that ``relaunch`` started, ``guarded`` writes the line to the launcher's file
(``MASSVIEW_RANK_ERRORS``), and the launcher prints it after the job (a CI run of
test_frame_pipeline's fault test once got an empty stderr, MPICH's own "Abort(1)" line lost with
the rank's). The end-to-end path, real ranks and a real abort, is that fault test; here the
rank's side runs in a process whose stderr is already gone, with a communicator whose Abort
ends the process as MPI_Abort does (the part under test is the code around it)."""

import os
import subprocess
import sys

from conftest import clean_env

RANK = r"""
import os, sys
from massview.parallel.runtime import guarded

class Comm:
    def __init__(self, rank, size):
        self.rank, self.size = rank, size
    def Get_rank(self):
        return self.rank
    def Get_size(self):
        return self.size
    def Abort(self, code):
        os._exit(code)

def fail():
    raise RuntimeError("boom at frame 7")

rank, size, close = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
if close:  # the rank's stderr is lost, as when hydra tears the job down first
    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 2)
guarded(Comm(rank, size), fail)
"""


def _rank(rank, size, close, errors=None):
    env = clean_env()
    if errors is not None:
        env["MASSVIEW_RANK_ERRORS"] = str(errors)
    return subprocess.run([sys.executable, "-c", RANK, str(rank), str(size), "1" if close else "0"], capture_output=True,
                          text=True, env=env, timeout=60)


def test_a_rank_of_a_relaunched_job_hands_its_error_to_the_launcher(tmp_path):
    errors = tmp_path / "errors.txt"
    errors.write_text("")
    for rank in (2, 1):
        proc = _rank(rank, 3, close=True, errors=errors)
        assert proc.returncode == 1
    lines = errors.read_text().splitlines()
    said = [ln for ln in lines if ln.startswith("massview: error on rank")]
    assert said == ["massview: error on rank 2 of 3: RuntimeError: boom at frame 7",
                    "massview: error on rank 1 of 3: RuntimeError: boom at frame 7"], lines
    assert "Traceback" in errors.read_text()


def test_without_the_launcher_file_or_alone_a_rank_prints_to_stderr(tmp_path):
    proc = _rank(1, 3, close=False)  # an external mpiexec: no file
    assert proc.returncode == 1 and "massview: error on rank 1 of 3: RuntimeError: boom at frame 7" in proc.stderr
    errors = tmp_path / "errors.txt"
    errors.write_text("")
    proc = _rank(0, 1, close=False, errors=errors)  # one rank: no MPI_Abort, its stderr is kept
    assert proc.returncode == 1 and "massview: error: RuntimeError: boom at frame 7" in proc.stderr
    assert errors.read_text() == ""
    gone = tmp_path / "no-such-folder" / "errors.txt"  # the file cannot be written: stderr after all
    proc = _rank(1, 3, close=False, errors=gone)
    assert proc.returncode == 1 and "error on rank 1 of 3" in proc.stderr


def test_the_launcher_prints_the_ranks_lines_after_the_job_and_removes_the_file(tmp_path):
    code = r"""
import sys
from massview.parallel import runtime

def job(cmd, env):  # stands for mpiexec: one rank wrote its line, the job failed
    with open(env[runtime.ERRORS_ENV], "a") as f:
        f.write("massview: error on rank 1 of 2: broken\n")
    print("left:", env[runtime.ERRORS_ENV], flush=True)
    return 1

runtime.run_job = job
sys.exit(runtime.relaunch(["render"], 2))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean_env(), timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip() == "massview: error on rank 1 of 2: broken", proc.stderr
    left = proc.stdout.split("left:", 1)[1].strip()
    assert not os.path.exists(left)


def test_without_a_writable_temporary_folder_the_job_still_runs():
    code = r"""
import sys, tempfile
from massview.parallel import runtime

def job(cmd, env):
    print("file:", env.get(runtime.ERRORS_ENV), flush=True)
    return 0

def full(*a, **k):
    raise OSError(28, "No space left on device")

runtime.run_job, tempfile.mkstemp = job, full
sys.exit(runtime.relaunch(["render"], 2))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean_env(), timeout=60)
    assert proc.returncode == 0 and "file: None" in proc.stdout, proc.stderr
