"""`massview view STORE --system roettger --compute-ranks C` in headless Chromium: the panel
shows T2's per-rank figures (LOD time, fans, triangles, bytes sent to each visualization rank),
with non-zero triangles on the computation ranks and the drawn count on the visualization rank."""

import pytest

from test_viewer import launch, start_viewer, stop_viewer

pytestmark = pytest.mark.mpi


def test_view_roettger_panel_shows_per_rank_figures(tmp_path):
    from playwright.sync_api import sync_playwright

    from massview.data.terrain import ArraySource, prepare_terrain
    from test_roettger import real_dem

    store = tmp_path / "real.zarr"
    prepare_terrain(ArraySource(real_dem(), "jacksboro", transform=(0.0, 80.0, 0.0, 0.0, 0.0, -80.0)), store, block=129, color=None)
    url, _, proc = start_viewer(store, ranks=3, size="320x240", extra=("--system", "roettger", "--compute-ranks", "2"))
    try:
        with sync_playwright() as p:
            browser = launch(p)
            page = browser.new_page()
            page.goto(url)
            page.wait_for_function("window.mv && window.mv.frames >= 2 && window.mv.stats && window.mv.stats.panel", timeout=90000)
            stats = page.evaluate("window.mv.stats")
            rows = stats["panel"]["rows"]
            assert [r[1] for r in rows] == ["visualization", "computation", "computation"]
            tri = stats["triangles_per_rank"]
            assert tri[0] == 0 and tri[1] + tri[2] > 0  # counted once, where they are produced
            assert sum(int(r[3]) for r in rows[1:]) > 0  # fans
            assert all(r[5].startswith("to vis ") and float(r[2]) >= 0 for r in rows[1:])
            assert float(rows[0][4].split()[1].rstrip("k")) * 1e3 == pytest.approx(tri[1] + tri[2], abs=100)  # drew them all
            assert page.evaluate("document.querySelectorAll('#sysrows tr').length") == 4  # header + 3 ranks
            assert "computation" in page.inner_text("#sysrows")
            browser.close()
    finally:
        stop_viewer(proc)
