"""Compositing and delivery under real mpiexec on random images, bit for bit against the serial
fold of ``combine`` (every compositor, 2-7 ranks: binary-swap folds 1-3 ranks in, rank 0 and a 2x2 wall, parts in many chunks,
pooled buffers reused across frames)."""

import subprocess
import sys
from pathlib import Path

import pytest

from conftest import clean_env

pytestmark = pytest.mark.mpi


@pytest.mark.parametrize("ranks", [2, 3, 4, 5, 6, 7])
def test_composite_and_deliver_equal_the_serial_fold(ranks):
    env = clean_env()
    mpiexec = str(Path(sys.executable).parent / "mpiexec")
    job = Path(__file__).parent / "composite_job.py"
    proc = subprocess.run([mpiexec, "-n", str(ranks), sys.executable, str(job), "1500"], capture_output=True, text=True,
                          env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "composite job ok" in proc.stdout
