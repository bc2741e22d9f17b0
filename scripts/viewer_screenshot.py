"""Make docs/viewer.png: ``massview view`` on the demo store (2 ranks, 1280x720, sort-last:kpatch
+ binary-swap, the defaults), shot in headless Chromium (Playwright, Debian's /usr/bin/chromium)
at 1200x700 with colour by rank ticked, after 20 more frames.

    python scripts/viewer_screenshot.py ~/.cache/massview/demo_terrain_4097.zarr docs/viewer.png

(the demo store is the one ``massview demo`` makes and keeps)."""

import os
import re
import shutil
import signal
import subprocess
import sys

from playwright.sync_api import sync_playwright


def main(store: str, png: str) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "massview", "view", store, "--ranks", "2", "--size", "1280x720", "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    line = ""
    while "serving http" not in line:
        line = proc.stdout.readline()
        if not line and proc.poll() is not None:
            sys.exit("massview view exited before serving")
    url = re.search(r"http://\S+", line).group(0)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=shutil.which("chromium"), headless=True, timeout=600000,
                                        args=["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                                              "--disable-background-networking", "--disable-component-update", "--disable-sync"])
            page = browser.new_page(viewport={"width": 1200, "height": 700})
            page.goto(url)
            page.wait_for_function("window.mv && window.mv.frames >= 2 && window.mv.stats", timeout=120000)
            page.check("#colorbyrank")
            page.wait_for_function("window.mv.stats.decomposition === 'sort-last:kpatch'", timeout=60000)
            n = page.evaluate("window.mv.frames")
            page.wait_for_function(f"window.mv.frames >= {n + 20}", timeout=300000)
            page.screenshot(path=png)
            browser.close()
    finally:
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C on the whole job
        proc.communicate(timeout=60)


if __name__ == "__main__":
    main(*sys.argv[1:3])
