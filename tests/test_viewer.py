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

from conftest import clean_env, stop_job

pytestmark = pytest.mark.mpi

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
if CHROMIUM is None and not os.environ.get("CI"):
    pytest.skip("chromium is not installed (apt-get install chromium); CI installs it", allow_module_level=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_viewer(store, ranks=2, host=None, size="480x270", extra=()):
    """``massview view STORE`` in its own session; returns (url, port, process) once it serves.
    ``extra``: further command-line arguments (e.g. ``--system dmmr``)."""
    port = free_port()
    env = clean_env()
    proc = subprocess.Popen([sys.executable, "-m", "massview", "view", str(store), "--ranks", str(ranks), "--port", str(port),
                             "--size", size] + (["--host", host] if host else []) + list(extra), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env, start_new_session=True)
    line = ""
    t0 = time.monotonic()
    try:
        while "serving http" not in line:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, "viewer exited early"
            assert time.monotonic() - t0 < 120, "the viewer did not serve within 120 s"
    except BaseException:
        stop_job(proc, timeout=10)  # (no job left running behind a failed start)
        raise
    return re.search(r"http://\S+", line).group(0), port, proc


def stop_viewer(proc):
    if proc.poll() is None:
        out = stop_job(proc)  # Ctrl-C on the whole job, as a terminal would; killed (and failed) if it does not stop
        assert proc.returncode == 0, out
        assert "viewer stopped" in out


@pytest.fixture()
def viewer(terrain_store):
    url, _, proc = start_viewer(terrain_store)
    yield url, proc
    stop_viewer(proc)


def launch(p):
    return p.chromium.launch(executable_path=CHROMIUM, headless=True,
                             args=["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                                   "--disable-background-networking", "--disable-component-update", "--disable-sync"])


def test_viewer_streams_reacts_and_survives_bad_input(viewer):
    from playwright.sync_api import sync_playwright

    url, proc = viewer
    with sync_playwright() as p:
        browser = launch(p)
        page = browser.new_page()
        errors = []  # (the page asked for /favicon.ico and logged its 404 on every load)
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.goto(url)
        page.wait_for_function("window.mv && window.mv.frames >= 2 && window.mv.stats", timeout=60000)
        assert not errors, errors
        assert page.evaluate("document.getElementById('decomposition').options.length") == 8  # 5 sort-first layouts (incl. balanced) + 3 sort-last

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


def _status(url, headers=None) -> int:
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=30) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code


def _ws_status(url, origin=None) -> int:
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    try:
        with connect(url, origin=origin, open_timeout=30) as ws:
            assert '"hello"' in ws.recv(timeout=30)
            return 101
    except InvalidStatus as e:
        return e.response.status_code


def test_off_loopback_needs_the_token_and_the_pages_origin(terrain_store):
    from playwright.sync_api import sync_playwright

    url, port, proc = start_viewer(terrain_store, ranks=1, host="0.0.0.0", size="320x180")
    try:
        token = re.search(r"token=([\w-]+)", url).group(1)
        base, ws = f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}/ws"
        assert len(token) >= 24
        assert _status(f"{base}/") == 403 and _status(f"{base}/?token=wrong") == 403 and _status(f"{base}/viewer.js") == 403
        assert _status(f"{base}/?token={token}") == 200
        assert _status(f"{base}/viewer.js", {"Cookie": f"massview_token={token}"}) == 200
        assert _ws_status(ws) == 403 and _ws_status(f"{ws}?token=wrong", origin=base) == 403
        assert _ws_status(f"{ws}?token={token}", origin="http://evil.example") == 403
        assert _ws_status(f"{ws}?token={token}", origin=base) == 101
        with sync_playwright() as p:  # the printed URL works in a browser (token -> cookie -> assets and WebSocket)
            browser = launch(p)
            page = browser.new_page()
            page.goto(f"{base}/?token={token}")
            page.wait_for_function("window.mv && window.mv.frames >= 2", timeout=60000)
            browser.close()
    finally:
        stop_viewer(proc)


MOVED = "(p) => window.mv.stats.position.some((v, i) => Math.abs(v - p[i]) > 1e-6)"


def test_loopback_refuses_foreign_origins_and_hosts_and_one_browser_steers(terrain_store):
    """Loopback: no token, but a foreign Origin (another site in the browser) or a foreign Host
    (DNS rebinding) gets 403. Two browsers: both watch, the first steers, the second takes over."""
    from playwright.sync_api import sync_playwright

    url, port, proc = start_viewer(terrain_store, ranks=1, size="320x180")
    try:
        base = f"http://127.0.0.1:{port}"
        assert _ws_status(f"ws://127.0.0.1:{port}/ws", origin="http://evil.example") == 403
        assert _ws_status(f"ws://127.0.0.1:{port}/ws", origin=base) == 101
        assert _status(f"{base}/", {"Host": f"evil.example:{port}"}) == 403
        with sync_playwright() as p:
            browser = launch(p)
            pilot, watcher = browser.new_page(), browser.new_page()
            pilot.goto(url)
            pilot.wait_for_function("window.mv && window.mv.role === 'pilot' && window.mv.frames >= 1", timeout=60000)
            watcher.goto(url)
            watcher.wait_for_function("window.mv && window.mv.role === 'watcher' && window.mv.frames >= 2", timeout=60000)
            start = watcher.evaluate("window.mv.stats")
            assert start["clients"] == 2
            watcher.evaluate("window.mv.ws.send(JSON.stringify({type: 'input', move: [1, 0, 0], look: [0, 0], dt: 1}))")
            watcher.wait_for_function("document.getElementById('message').textContent.includes('watching')", timeout=60000)
            watcher.wait_for_function(f"window.mv.stats.frame > {start['frame'] + 2}", timeout=60000)
            assert watcher.evaluate("window.mv.stats.position") == start["position"]  # a watcher does not steer
            pilot.evaluate("window.mv.ws.send(JSON.stringify({type: 'input', move: [1, 0, 0], look: [0, 0], dt: 1}))")
            watcher.wait_for_function(MOVED, arg=start["position"], timeout=60000)  # the pilot's input moves what everyone sees
            moved = watcher.evaluate("window.mv.stats.position")
            pilot.close()
            watcher.wait_for_function("window.mv.role === 'pilot'", timeout=60000)  # the watcher takes over
            watcher.evaluate("window.mv.ws.send(JSON.stringify({type: 'input', move: [1, 0, 0], look: [0, 0], dt: 1}))")
            watcher.wait_for_function(MOVED, arg=moved, timeout=60000)
            browser.close()
    finally:
        stop_viewer(proc)


def _cpu_seconds(port: int) -> dict:
    """CPU seconds (user + system) of every process whose command line has ``--port port``."""
    out, tick = {}, os.sysconf("SC_CLK_TCK")
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmd = f.read().split(b"\0")
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if b"--port" in cmd and str(port).encode() in cmd and b"view" in cmd:
            out[pid] = (int(fields[11]) + int(fields[12])) / tick
    return out


def test_with_no_page_open_the_ranks_render_nothing_and_do_not_spin(terrain_store):
    """Nobody watching: no frame is rendered, and the ranks wait without spinning a core (they
    rendered on at 40–75 % CPU each; an MPI bcast busy-polls)."""
    url, port, proc = start_viewer(terrain_store)
    try:
        time.sleep(3.0)  # (start-up work done)
        before = _cpu_seconds(port)
        time.sleep(4.0)
        after = _cpu_seconds(port)
    finally:
        out = stop_job(proc)
    assert "viewer stopped after 0 frames" in out, out[-2000:]
    used = {p: after[p] - before[p] for p in before if p in after}
    assert len(used) >= 2 and max(used.values()) < 1.0, used  # a spinning rank would take ~4 CPU-s (2 at least on 2 busy cores)
