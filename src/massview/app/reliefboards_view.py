"""``massview view SCENE --system reliefboards --ranks N``: M2 live in the browser.

The visualization rank serves the page and renders with the browser's fly camera; the backends
serve board requests as in ``massview render``. "colour by rank" tints every board by the
backend that built it. The overlay shows, besides fps and triangles, the requests in flight per
backend, the requests answered, and a histogram of the angle errors of the boards drawn over
the last 30 frames (5° bins up to E). There is no per-frame broadcast: the backends never wait
for the visualization rank, nor it for them; Ctrl-C stops the job (the visualization rank sends
STOP to the backends and drains their last boards).
"""

from __future__ import annotations

import io
import logging
import signal
import sys
import time
from collections import deque

import numpy as np

from ..core.config import RenderConfig
from ..systems import scene_kind
from .view_cmd import start_camera

__all__ = ["run_view_reliefboards"]

HIST_BINS = np.arange(0.0, 50.0, 5.0)


def _jpeg(image, quality: int = 80) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image.color[..., :3]).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def run_view_reliefboards(comm, args, cfg: RenderConfig, opts) -> int:
    from ..parallel.roles import split_roles
    from ..systems.boardscene import open_board_objects
    from ..systems.reliefboards import ROLES, BackendRank

    objects = open_board_objects(args.scene, opts.cluster_params(cfg.height, 45.0))
    rc = split_roles(comm, ROLES)
    viz, backends = rc.leader("visualization"), rc.ranks["backend"]
    if rc.role == "backend":
        signal.signal(signal.SIGINT, lambda *a: None)  # the visualization rank stops us
        signal.signal(signal.SIGTERM, lambda *a: None)
        rc.parent.gather(BackendRank(rc.parent, viz, backends, objects, opts, cfg.egl_device).run(), root=viz)
        return 0
    frames = _serve(rc.parent, backends, objects, opts, args, cfg)
    rc.parent.gather(None, root=viz)
    print(f"massview: viewer stopped after {frames} frames", flush=True)
    return 0


def _panel(c: dict, answered: int, angles) -> dict:
    """The M2 figures of the viewer's overlay."""
    return {"in_flight": c["pending_by_backend"], "answered": answered, "boards": c["boards_drawn"],
            "far_originals": c["far_original"], "angle_hist": np.sum(angles, axis=0).tolist(), "angle_bins": HIST_BINS.tolist()}


def _serve(parent, backends, objects, opts, args, cfg: RenderConfig) -> int:
    from ..systems.reliefboards import VisualizationRank
    from .viewer import ViewerServer, ViewerState

    stop = {"flag": False}
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *a: stop.update(flag=True))
    logging.basicConfig(level=logging.WARNING, format="massview viewer: %(message)s", stream=sys.stderr)
    lo, hi = objects.bounds
    start = start_camera(scene_kind(args.scene), lo, hi, cfg.width, cfg.height)
    settings = {"decomposition": "reliefboards", "compositor": "none", "tau": cfg.tau, "color_by_rank": cfg.color_by_rank}
    state = ViewerState(start, settings, {"decomposition": ["reliefboards"], "compositor": ["none"]},
                        float(np.linalg.norm((hi - lo)[:2])) * 0.02)
    server = ViewerServer(state, args.host, args.port)
    vis = VisualizationRank(parent, backends, objects, opts, cfg.egl_device, cfg.color_by_rank)
    server.start()
    print(f"massview: serving http://{args.host}:{server.port}/ (reliefboards: 1 visualization rank, "
          f"{len(backends)} backends; Ctrl-C stops)", flush=True)
    times, angles = deque(maxlen=20), deque(maxlen=30)
    frame, answered = 0, 0
    try:
        while not stop["flag"]:
            snap = state.snapshot()
            if snap["stop"]:
                break
            vis.tint_boards = bool(snap["settings"].get("color_by_rank"))
            t0 = time.perf_counter()
            image, stats = vis.frame(snap["camera"], frame)
            times.append(time.perf_counter() - t0)
            answered += int(stats.counters.get("answered", 0))
            angles.append(np.histogram(stats.counters["angle_error"], HIST_BINS)[0])
            server.publish(_jpeg(image), {
                "frame": frame, "fps": len(times) / sum(times), "triangles_per_rank": [stats.triangles], "imbalance": 1.0,
                "bytes_per_frame": stats.bytes_recv, "decomposition": "reliefboards", "compositor": "none", "tau": cfg.tau,
                "color_by_rank": vis.tint_boards, "position": state.position(), "rejected": state.rejected, "clients": server.clients,
                "m2": _panel(stats.counters, answered, angles)})
            if server.clients == 0:
                time.sleep(0.05)
            frame += 1
    finally:
        vis.close()
        server.stop()
    return frame
