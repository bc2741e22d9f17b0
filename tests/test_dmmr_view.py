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


_FRAME_PIXELS = """async () => { for (let k = 0; k < 50; k++) {  // the frame on show, decoded (retried when a newer one replaces it)
  const im = new Image(); im.src = document.getElementById('frame').src;
  try { await im.decode(); } catch (e) { continue; }
  const c = document.createElement('canvas'); c.width = im.naturalWidth; c.height = im.naturalHeight;
  const g = c.getContext('2d'); g.drawImage(im, 0, 0);
  return [c.width, c.height, Array.from(g.getImageData(0, 0, c.width, c.height).data)]; } return null; }"""


def _frame_after(page, frames: int = 3):
    """The viewer's current frame (RGB uint8) once ``frames`` more have arrived."""
    import numpy as np

    n = page.evaluate("window.mv.frames")
    page.wait_for_function(f"window.mv.frames >= {n + frames}", timeout=120000)
    w, h, px = page.evaluate(_FRAME_PIXELS)
    return np.asarray(px, np.uint8).reshape(h, w, 4)[..., :3].astype(np.float64)


def _split(page) -> tuple[str, list[tuple[int, int, int, int]]]:
    rows = dict(page.evaluate("window.mv.stats.panel.rows"))
    return rows["split"], [tuple(int(v) for v in part.split(",")) for part in rows["sub-frusta x,y,w,h per client"].split(" / ")]


def _tints_by_region(plain, tinted, regions):
    """Per client region (x, y, w, h; top-left origin): the tint the frame shows there, estimated
    on object pixels from tinted = (1 − a)·plain + a·tint (a = 0.55), median per channel, 0..1."""
    import numpy as np

    out = []
    for x, y, w, h in regions:
        p, t = plain[y:y + h, x:x + w].reshape(-1, 3), tinted[y:y + h, x:x + w].reshape(-1, 3)
        obj = np.abs(t - p).sum(1) > 40  # pixels the tint changed: objects (the sky is not tinted)
        assert obj.sum() > 50, (x, y, w, h)
        out.append(np.median((t[obj] - 0.45 * p[obj]) / 0.55, axis=0) / 255)
    return out


def test_dmmr_viewer_switches_the_split_and_shows_each_clients_tint_in_its_region():
    """The decomposition menu offers what applies to M1 (Algorithm 1 or equal tiles) and switches
    the running server's split; with colour-by-client each client's sub-frustum, as the server
    reports it, shows that client's tint in the streamed frame."""
    import numpy as np
    from playwright.sync_api import sync_playwright

    from massview.parallel.decompose import sort_first_tiles
    from massview.render.meshes import rank_tint
    from massview.systems.dmmr import DmmrSystem

    W, H = 320, 180
    url, _, proc = start_viewer("builtin:objects?n=300&seed=4", ranks=3, size=f"{W}x{H}", extra=("--system", "dmmr"))
    try:
        with sync_playwright() as p:
            browser = launch(p)
            page = browser.new_page()
            page.goto(url)
            page.wait_for_function("window.mv && window.mv.stats && window.mv.stats.panel && "
                                   "Object.fromEntries(window.mv.stats.panel.rows)['split']", timeout=120000)
            options = page.evaluate("[...document.getElementById('decomposition').options].map((o) => o.value)")
            assert options == list(DmmrSystem.viewer_decompositions)  # no sort-last: it does not apply to M1
            assert page.input_value("#decomposition") == "sort-first:kd"
            assert "Algorithm 1" in page.get_attribute("#decomposition", "title")
            name, regions = _split(page)
            assert name == "Algorithm 1" and len(regions) == 2 and sum(w * h for _, _, w, h in regions) == W * H

            plain = _frame_after(page)
            page.check("#colorbyrank")
            page.wait_for_function("window.mv.stats.color_by_rank === true", timeout=60000)
            tinted = _frame_after(page)
            tints = [np.asarray(rank_tint(c)[:3]) for c in range(2)]
            for c, seen in enumerate(_tints_by_region(plain, tinted, regions)):
                dist = [float(np.abs(seen - t).max()) for t in tints]
                assert dist[c] < 0.12 and dist[c] < dist[1 - c], (c, seen, dist)

            page.select_option("#decomposition", "sort-first:horizontal")
            page.wait_for_function("Object.fromEntries(window.mv.stats.panel.rows)['split'] === 'equal tiles (horizontal)'", timeout=60000)
            _, regions = _split(page)
            assert regions == [(v.x, v.y, v.w, v.h) for v in sort_first_tiles("horizontal", 2, W, H)]
            assert page.evaluate("window.mv.stats.decomposition") == "sort-first:horizontal"
            tinted = _frame_after(page)
            page.uncheck("#colorbyrank")
            page.wait_for_function("window.mv.stats.color_by_rank === false", timeout=60000)
            plain = _frame_after(page)
            for c, seen in enumerate(_tints_by_region(plain, tinted, regions)):
                assert float(np.abs(seen - tints[c]).max()) < 0.12, (c, seen)
            browser.close()
    finally:
        stop_viewer(proc)
