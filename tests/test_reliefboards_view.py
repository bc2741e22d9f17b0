"""`massview view --system reliefboards` end to end in headless Chromium: the stream runs, the
panel shows requests in flight and the angle-error histogram, boards get tinted on request,
Ctrl-C stops every rank."""

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.mpi

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
if CHROMIUM is None and not os.environ.get("CI"):
    pytest.skip("chromium is not installed (apt-get install chromium); CI installs it", allow_module_level=True)


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_reliefboards_viewer_panel_and_tint():
    from playwright.sync_api import sync_playwright

    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI_", "HYDRA_", "MASSVIEW_"))}
    proc = subprocess.Popen([sys.executable, "-m", "massview", "view", "builtin:objects?n=100", "--system", "reliefboards",
                             "--ranks", "3", "--port", str(_port()), "--size", "320x240", "--tnz", "5000", "--board-px", "32",
                             "--min-triangles", "100"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            start_new_session=True)
    try:
        line, t0 = "", time.monotonic()
        while "serving http" not in line:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, "viewer exited early"
            assert time.monotonic() - t0 < 120
        url = re.search(r"http://\S+", line).group(0)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox", "--disable-gpu"])
            page = browser.new_page()
            page.goto(url)
            page.wait_for_function("window.mv && window.mv.stats && window.mv.stats.m2 && window.mv.stats.m2.answered > 0",
                                   timeout=120000)
            assert page.is_visible("#m2")
            m2 = page.evaluate("window.mv.stats.m2")
            assert len(m2["in_flight"]) == 2 and len(m2["angle_hist"]) == 9
            page.check("#colorbyrank")
            page.wait_for_function("window.mv.stats.color_by_rank === true", timeout=60000)
            browser.close()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert "viewer stopped" in out
