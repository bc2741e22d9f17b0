"""The web viewer end to end, in headless Chromium driven by Playwright (no browser download:
Debian's /usr/bin/chromium)."""

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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture()
def viewer(terrain_store):
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI_", "HYDRA_", "MASSVIEW_"))}
    proc = subprocess.Popen([sys.executable, "-m", "massview", "view", str(terrain_store), "--ranks", "2", "--port", str(port),
                             "--size", "480x270"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            start_new_session=True)
    line = ""
    t0 = time.monotonic()
    while "serving http" not in line:
        line = proc.stdout.readline()
        assert line or proc.poll() is None, "viewer exited early"
        assert time.monotonic() - t0 < 120
    url = re.search(r"http://\S+", line).group(0)
    yield url, proc
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C on the whole job, as a terminal would
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0, out
        assert "viewer stopped" in out


def test_viewer_streams_reacts_and_survives_bad_input(viewer):
    from playwright.sync_api import sync_playwright

    url, proc = viewer
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True,
                                    args=["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                                          "--disable-background-networking", "--disable-component-update", "--disable-sync"])
        page = browser.new_page()
        page.goto(url)
        page.wait_for_function("window.mv && window.mv.frames >= 2 && window.mv.stats", timeout=60000)
        assert page.evaluate("document.getElementById('decomposition').options.length") == 7

        # a key press changes the next frames (the camera moves)
        before = page.evaluate("window.mv.stats")
        page.click("#view")
        page.keyboard.down("w")
        page.wait_for_timeout(800)
        page.keyboard.up("w")
        page.wait_for_function(f"window.mv.stats.frame > {before['frame'] + 2}", timeout=60000)
        after = page.evaluate("window.mv.stats")
        assert after["position"] != before["position"]

        # switching the decomposition changes the per-rank figures
        page.select_option("#decomposition", "sort-first:vertical")
        page.wait_for_function("window.mv.stats.decomposition === 'sort-first:vertical'", timeout=60000)
        page.wait_for_function("window.mv.stats.frame > 0", timeout=60000)
        sf = page.evaluate("window.mv.stats")
        page.select_option("#decomposition", "sort-last:kpatch")
        page.wait_for_function("window.mv.stats.decomposition === 'sort-last:kpatch'", timeout=60000)
        sl = page.evaluate("window.mv.stats")
        assert sf["triangles_per_rank"] != sl["triangles_per_rank"]
        assert max(sl["triangles_per_rank"]) - min(sl["triangles_per_rank"]) <= 256 * 2  # kpatch shares

        # malformed and hostile messages are rejected; the stream goes on
        frames = page.evaluate("window.mv.frames")
        page.evaluate("""() => { const ws = window.mv.ws;
            ws.send('{not json'); ws.send(JSON.stringify({type: 'settings', tau: 1e9}));
            ws.send(JSON.stringify({type: 'input', move: [5, 0, 0], look: [0, 0]}));
            ws.send(JSON.stringify({type: 'explode'})); }""")
        page.wait_for_function(f"window.mv.frames > {frames + 3} && window.mv.stats.rejected >= 4", timeout=60000)
        assert "rejected" in page.inner_text("#message")
        browser.close()
    assert proc.poll() is None  # closing the page did not stop the job
