"""M1 in the live viewer (`massview view SCENE --system dmmr`): real mpiexec ranks (server +
clients), headless Chromium; the panel shows the system's figures."""

import pytest

from test_viewer import CHROMIUM, launch, start_viewer, stop_viewer  # noqa: F401 - skips without chromium

pytestmark = pytest.mark.mpi


def test_dmmr_viewer_panel_shows_the_clients_figures():
    from playwright.sync_api import sync_playwright

    url, _, proc = start_viewer("builtin:objects?n=300&seed=4", ranks=3, size="320x180", extra=("--system", "dmmr"))
    try:
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
