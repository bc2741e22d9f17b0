"""M1 in the live viewer (`massview view SCENE --system dmmr`): real mpiexec ranks (server +
clients), headless Chromium; the panel shows the system's figures."""

import os
import re
import subprocess
import sys

import pytest

from test_viewer import CHROMIUM, free_port, launch, stop_viewer  # noqa: F401 - skips without chromium

pytestmark = pytest.mark.mpi


def test_dmmr_viewer_panel_shows_the_clients_figures():
    from playwright.sync_api import sync_playwright

    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI_", "HYDRA_", "MASSVIEW_"))}
    proc = subprocess.Popen([sys.executable, "-m", "massview", "view", "builtin:objects?n=300&seed=4", "--system", "dmmr",
                             "--ranks", "3", "--port", str(port), "--size", "320x180"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, start_new_session=True)
    try:
        line = ""
        while "serving http" not in line:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, "viewer exited early"
        url = re.search(r"http://\S+", line).group(0)
        with sync_playwright() as p:
            browser = launch(p)
            page = browser.new_page()
            page.goto(url)
            page.wait_for_function("window.mv && window.mv.stats && window.mv.stats.panel", timeout=120000)
            page.wait_for_function("Object.fromEntries(window.mv.stats.panel.rows)['cache GPU hits/RAM hits/disk loads']"
                                   ".split(' · ').length === 2", timeout=120000)
            rows = dict(page.evaluate("window.mv.stats.panel.rows"))
            text = page.inner_text("#sysrows")
            browser.close()
        assert "occlusion queries / culled" in rows and "ms divide · visibility · render · assemble" in rows
        assert int(rows["M1 objects in frustum / sent"].split(" / ")[0]) > 0
        assert len(rows["received per client"].split("/")) == 2  # two clients
        assert "M1 objects in frustum / sent" in text
    finally:
        stop_viewer(proc)
