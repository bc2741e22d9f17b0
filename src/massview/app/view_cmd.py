"""``massview view STORE --ranks N``: live parallel rendering streamed to a browser.

Rank 0 serves the page (127.0.0.1 unless ``--host`` says otherwise; off loopback a random
token in the printed URL is required, see :mod:`.viewer.server`) and holds the camera and
settings the browser controls; every frame it broadcasts them, all ranks render the frame
with the chosen decomposition and compositor, and rank 0 streams the composited image as JPEG
with per-frame figures (fps, triangles per rank, imbalance, bytes per frame). With no page
open the ranks render nothing and wait without spinning (they kept rendering at 40–75 % CPU
each). Closing the page does not stop the job; Ctrl-C (SIGINT to the ranks) stops every rank
at the next frame. The first view is :func:`start_camera`'s.
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
from .viewer.state import VIEWER_COLORMAPS
from ..core.framing import overview_camera
from ..core.paths import load_path
from ..parallel.composite import COMPOSITORS
from ..parallel.decompose import SORT_FIRST_LAYOUTS, parse_decomposition
from ..parallel.exchange import any_rank, polite_bcast
from ..systems import render_frame

__all__ = ["run_view", "start_camera"]


def start_camera(kind: str, lo, hi, width: int, height: int):
    """The viewer's first camera for a scene of ``kind`` (:func:`massview.systems.scene_kind`)
    in the box ``lo``..``hi``: a scene store's frames the whole box, centred
    (:func:`massview.core.framing.overview_camera`) — ``flyover``'s start left a glTF assembly
    cut at the right edge and showed a single object's corner at the bottom right; a terrain's
    and ``builtin:objects``' (wide, flat fields) stay the start of ``flyover``, low over the
    west end looking along it."""
    if kind == "scene":
        return overview_camera(lo, hi, width, height)
    return load_path("flyover", lo, hi).camera(0.0, width, height)


def _jpeg(tile, quality: int = 80) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(tile.color[..., :3]).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def run_view(comm, args, cfg: RenderConfig) -> int:
    from ..api import open_scene

    rank, n = comm.Get_rank(), comm.Get_size()
    stop = {"flag": False}

    def on_sigint(signum, frame):
        stop["flag"] = True

    signal.signal(signal.SIGINT, on_sigint)  # first: a stop while a rank still opens the scene ends the loop at
    signal.signal(signal.SIGTERM, on_sigint)  # its first test, as a clean stop (it interrupted that rank's setup)
    scene = open_scene(args.scene)
    system = scene.system(cfg)
    server = state = None
    if rank == 0:
        from .viewer import ViewerServer, ViewerState

        logging.basicConfig(level=logging.WARNING, format="massview viewer: %(message)s", stream=sys.stderr)
        relief = None  # a terrain drawn at an exaggeration the browser may change: its box at 1×, kept by the state
        if hasattr(system, "bounds_at"):  # (walk7 H1: the start was fitted to the 1× box, under a relief drawn at 5×)
            relief = system.bounds_at(RenderConfig(**{**cfg.to_json(), "exaggeration": 1.0}))
        lo, hi = system.bounds_at(cfg) if relief is not None else system.bounds
        start = start_camera(scene.kind, lo, hi, cfg.width, cfg.height)
        modes = [f"sort-first:{m}" for m in SORT_FIRST_LAYOUTS] + (
            [f"sort-last:{m}" for m in system.sort_last_modes] if system.sort_last_modes else ["sort-last"])
        kind, mode = parse_decomposition(cfg.decomposition, system.sort_last_modes)
        settings = {"decomposition": f"{kind}:{mode}" if mode else kind,
                    "compositor": cfg.compositor, "tau": cfg.tau, "color_by_rank": cfg.color_by_rank,
                    "exaggeration": cfg.exaggeration, "sun": list(cfg.sun), "colormap": cfg.colormap, "haze": cfg.haze}
        modes = list(getattr(system, "viewer_decompositions", modes))  # a system may offer only what applies to it (M1)
        if settings["decomposition"] not in modes:
            settings["decomposition"] = modes[0]
        base_speed = float(np.linalg.norm((hi - lo)[:2])) * 0.02
        cmaps = list(dict.fromkeys([cfg.colormap, *VIEWER_COLORMAPS]))
        state = ViewerState(start, settings, {"decomposition": modes, "compositor": list(COMPOSITORS), "colormap": cmaps,
                                              "decomposition_note": getattr(system, "viewer_note", "")}, base_speed,
                            relief)
        server = ViewerServer(state, args.host, args.port)
        server.start()
    comm.Barrier()  # every rank set up, its stop handler in place, before the URL is announced (a stop right after
    if rank == 0:   # "serving" reached a rank still opening the scene: exit 143 instead of a clean stop)
        bound = "" if server.loopback else f"; bound to {args.host}, the token in the URL is required"
        print(f"massview: serving {server.url} on {n} rank{'s' if n > 1 else ''} (Ctrl-C stops{bound})", flush=True)
    times: deque = deque(maxlen=20)
    frame, idle = 0, False
    try:
        while True:
            snap = None
            if rank == 0:
                snap = state.snapshot()
                snap["idle"] = server.clients == 0
                if snap["idle"]:
                    time.sleep(0.1)  # nobody watching: render nothing, answer a new client within 0.1 s
            # (the other ranks wait without spinning a core: up to 10 ms between tests while idle,
            # 0.5 ms while frames are drawn, so a frame starts at most that much late)
            snap = polite_bcast(comm, snap, longest_sleep=0.01 if idle else 5e-4)
            if any_rank(comm, stop["flag"] or snap["stop"]):
                break
            idle = snap["idle"]
            if idle:
                continue
            fcfg = RenderConfig(**{**cfg.to_json(), **snap["settings"], "grid": cfg.grid})
            t0 = time.perf_counter()
            res = render_frame(comm, system, fcfg, snap["camera"], frame)
            recs = comm.gather(res.stats.to_json(), root=0)
            times.append(time.perf_counter() - t0)
            if rank == 0:
                tri = [r["triangles"] for r in sorted(recs, key=lambda r: r["rank"])]
                mean = float(np.mean(tri)) if tri else 0.0
                server.publish(_jpeg(res.tile), {
                    "frame": frame, "fps": len(times) / sum(times), "triangles_per_rank": tri,
                    "imbalance": (max(tri) / mean) if mean > 0 else 1.0, "bytes_per_frame": sum(r["bytes_sent"] for r in recs),
                    "decomposition": fcfg.decomposition, "compositor": fcfg.compositor, "tau": fcfg.tau,
                    "color_by_rank": fcfg.color_by_rank, "position": state.position(), "rejected": state.rejected,
                    "clients": server.clients, "panel": system.panel(recs) if hasattr(system, "panel") else None})
            frame += 1
    finally:
        scene.close()
        if server is not None:
            server.stop()
    if rank == 0:
        print(f"massview: viewer stopped after {frame} frames", flush=True)
    return 0
