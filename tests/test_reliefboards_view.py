"""`massview view --system reliefboards` end to end in headless Chromium: the stream runs, the
panel shows requests in flight and the angle-error histogram, boards get tinted on request,
Ctrl-C stops every rank."""


import pytest

from conftest import stop_job
from test_viewer import CHROMIUM, launch, start_viewer  # noqa: F401 - skips without chromium

pytestmark = pytest.mark.mpi


def test_reliefboards_viewer_panel_and_tint():
    from playwright.sync_api import sync_playwright

    url, _, proc = start_viewer("builtin:objects?n=100", ranks=3, size="320x240",
                                extra=("--system", "reliefboards", "--tnz", "5000", "--board-px", "32", "--min-triangles", "100"))
    try:
        with sync_playwright() as p:
            browser = launch(p)
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
        out = stop_job(proc, timeout=120)
    assert proc.returncode == 0, out
    assert "viewer stopped" in out
