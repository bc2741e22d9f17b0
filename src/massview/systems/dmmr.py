"""M1 — Distributed Massive Model Rendering (Revanth & Narayanan, ICVGIP 2012).

Roles (§3.1): rank 0 is the **server**, every other rank a **client** (one rank: the server
and one client share the process, linked by queues instead of MPI).

* Server, per frame (§3.4): frustum-cull the skeleton (hierarchical, over group boxes), choose
  each object's LOD level from ``--tau``, split the screen into one sub-frustum per client with
  the load-balanced frustum division (Algorithm 1, :mod:`massview.lod.split`, weights =
  triangles of the chosen levels, footprints = projected bounding spheres) and send each client
  its viewport and object list (``--decomposition sort-first:horizontal|vertical|grid`` uses
  equal screen tiles instead: the baseline Algorithm 1 is measured against). The server holds
  the skeleton only and never reads geometry (except to render the one-rank reference under
  ``--reference``).
* Client (§3.5–3.8, :mod:`massview.systems.dmmr_client`): occlusion culling on GPU 1,
  sub-frame rendering through the GPU/RAM/disk cache on GPU 2, compress, send.
* Server, assembly (§3.7): receive, decompress and paste the sub-frames; deliver the frame.

Pipelining (§3.3): with ``--stage-pipeline on`` (default) the server divides frame i while
the clients determine the visibility of frame i−1 and render frame i−2 (one thread per module,
:class:`~massview.parallel.pipeline.StagePipeline` on the clients, at most three frames in
flight); ``off`` runs one frame at a time (the synchronous reference).

Statistics per frame: the server's record (rank 0) has stages ``divide``, ``send``,
``assemble`` and ``total`` = the frame period (time between consecutive delivered frames), and
counters for objects in the frustum and sent, latency (ms and frames in flight); each client's
record has stages ``visibility`` (``vis_load``, ``vis_issue``, ``vis_retrieve``), ``load``,
``draw``, ``readback``, ``encode``, ``send`` and counters for queries issued and waits, objects
culled by occlusion, triangles drawn, cache hits and loads per level and bytes. Both carry the
process counters of :class:`~massview.systems.dmmr_meter.ProcessMeter` (``cpu_ms``,
``file_read_bytes``, ``device_read_bytes``: between two delivered frames); a client's also
``frame_mesh_bytes`` and ``depth_mesh_bytes`` (decoded bytes of the meshes drawn and of the
depth pre-pass). The server hands frames to ``sink`` through a
:class:`~massview.systems.frameloop.SinkThread` (PNG writing off the frame period).
"""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np

from ..core.camera import Camera
from ..core.config import RenderConfig
from ..core.errors import ConfigError
from ..core.image import Image, blank_image
from ..core.stats import FrameStats
from ..data.cache import BlockCache
from ..lod.scene import SkeletonCuller, choose_levels
from ..lod.split import assign_to_tiles, divide_frustum, sphere_rects
from ..parallel.codec import decode_image
from ..parallel.decompose import parse_decomposition, sort_first_tiles
from ..parallel.pipeline import StagePipeline
from ..parallel.roles import run_roles, split_roles
from ..render.geometry_cache import packed_loader
from ..render.meshes import rank_tint
from .dmmr_client import ClientTask, DmmrClient, SceneDrawer
from .dmmr_links import ROLES, LocalLink, MpiLink
from .dmmr_meter import ProcessMeter
from .dmmr_panel import panel_rows
from .dmmr_scene import open_scene
from .frameloop import SinkThread, image_diff

__all__ = ["DmmrSystem", "DmmrServer"]

def _delays(cfg: RenderConfig) -> dict[str, float]:
    """``--stage-delay divide:MS,visibility:MS,render:MS`` (testing aid) in seconds."""
    out = {}
    for part in (cfg.stage_delay or "").split(","):
        if part:
            name, _, ms = part.partition(":")
            out[name] = float(ms) / 1e3
    return out


class DmmrServer:
    """Frustum culling, level choice and Algorithm 1 over the skeleton only."""

    def __init__(self, store, tau: float, layout: str = "balanced", grid=None):
        self.layout, self.grid = layout, grid
        sk = self.sk = store.skeleton
        self.culler = SkeletonCuller(store.groups, sk.group, sk.box_lo, sk.box_hi)
        self.levels = np.asarray(sk.levels, np.int64)
        self.tris = np.asarray(sk.triangles, np.int64)
        self.tau = tau

    def cut(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Object ids in the frustum (sorted) and their chosen levels."""
        vis = np.flatnonzero(self.culler.visible(camera.frustum_planes()))
        sk = self.sk
        lv = choose_levels(camera, sk.center[vis], sk.radius[vis], self.levels[vis], sk.level_error[vis], self.tau)
        return vis, np.asarray(lv, np.int64)

    def divide(self, frame: int, camera: Camera, clients: int) -> tuple[list[ClientTask], np.ndarray, np.ndarray]:
        vis, lv = self.cut(camera)
        rects = sphere_rects(camera, self.sk.center[vis], self.sk.radius[vis])
        weights = self.tris[vis, lv].astype(np.float64)
        if self.layout == "balanced":
            subs = divide_frustum(rects, weights, camera.viewport, clients)
        else:  # equal screen tiles: the baseline Algorithm 1 is compared with
            tiles = sort_first_tiles(self.layout, clients, camera.width, camera.height, self.grid)
            subs = assign_to_tiles(rects, weights, tiles)
        tasks = [ClientTask(frame, camera, s.viewport, vis[s.items], lv[s.items]) for s in subs]
        return tasks, vis, lv


NO_WALL = "--wall and --tile-targets are not available with --system dmmr (the server assembles one frame); leave them out"


class DmmrSystem:
    """``--system dmmr``: see the module doc. ``run_path`` is the system's own frame loop."""

    sort_last_modes: tuple[str, ...] = ()

    def __init__(self, spec: str, cfg: RenderConfig | None = None):
        self.spec = spec
        self.cfg = cfg or RenderConfig()
        if self.cfg.wall or self.cfg.tile_targets:
            raise ConfigError(NO_WALL)
        self.store = open_scene(spec)
        self.server = DmmrServer(self.store, self.cfg.tau, self._layout(self.cfg), self.cfg.grid)
        self._ref: SceneDrawer | None = None
        self._split: list = []  # the last frame's client viewports (the viewer's panel)
        self._on_record = None  # run_path's callback for the server's record of each frame
        self._client_gl: str | None = None  # the clients' GL renderer strings, once run_path has gathered them

    #: what the viewer's decomposition menu offers: the server splits the frustum itself, with
    #: Algorithm 1 (the runtime's ``kd`` slot) or into equal screen tiles; sort-last does not
    #: apply (each client draws its own screen region)
    viewer_decompositions = ("sort-first:kd", "sort-first:horizontal", "sort-first:vertical", "sort-first:grid")
    viewer_note = "M1: sort-first:kd = Algorithm 1 (load-balanced frustum division); the others: equal screen tiles"

    @staticmethod
    def _layout(cfg: RenderConfig) -> str:
        """``balanced`` (Algorithm 1: sort-last, the default, or ``sort-first:kd``/``balanced``) or
        an equal-tile layout (``sort-first:horizontal|vertical|grid``)."""
        kind, layout = parse_decomposition(cfg.decomposition, ("default",))
        return "balanced" if kind == "sort-last" or layout == "kd" else layout

    work_roles = ("client",)  # the ranks whose triangles the summary's imbalance compares

    @staticmethod
    def rank_roles(n: int) -> list[str]:
        """Each of the ``n`` ranks' role: rank 0 the server, the others clients (one rank is both)."""
        return ["server"] + ["client"] * (n - 1) if n > 1 else ["server and client"]

    def split_label(self, cfg: RenderConfig) -> tuple[str, str]:
        """(decomposition, compositor) as the summary names them: the server divides the
        frustum (Algorithm 1, load-balanced, or equal tiles) and assembles the clients'
        sub-frames."""
        kind, _ = parse_decomposition(cfg.decomposition, ("default",))
        return (cfg.decomposition if kind == "sort-first" else "sort-first:balanced"), "sub-frame assembly"

    @property
    def bounds(self):
        lo, hi = self.store.bounds
        return np.asarray(lo, np.float64), np.asarray(hi, np.float64)

    @property
    def obstacles(self):
        """The objects' boxes, which the ``walkthrough`` path walks round."""
        return self.store.object_boxes

    @property
    def renderer(self) -> str:
        """What draws: the server and its clients, with the clients' GL renderer (known on rank 0
        after :meth:`run_path`; the server itself has no GL context)."""
        gl = self._client_gl
        return "dmmr: server + clients (each: occlusion-query and render GL contexts)" + (f"; clients' GL: {gl}" if gl else "")

    def ram_budget(self, clients: int) -> int:
        """Client RAM cache bytes: ``--client-cache-mb`` or the scene's object bytes ÷ clients (§4)."""
        if self.cfg.client_cache_mb:
            return self.cfg.client_cache_mb << 20
        lb = np.asarray(self.store.skeleton.level_bytes, np.int64)
        return max(int(lb.sum()) // max(clients, 1), 4 * int(lb.max(initial=0)) + (1 << 20))  # at least a few meshes

    # -- the frame loop -----------------------------------------------------------------
    def run_path(self, comm, cameras: list[Camera] | None, cfg: RenderConfig, sink=None, on_record=None):
        """Render ``cameras`` (rank 0's list); returns (records, diffs) on rank 0, else None.
        ``on_record(record)``: called on rank 0 with the server's record of each frame as it is
        finished (the clients' records come with the result, at the end), so a run stopped
        part-way keeps its finished frames' statistics."""
        self._on_record = on_record
        rank, size = comm.Get_rank(), comm.Get_size()
        clients = max(size - 1, 1)
        nframes = comm.bcast(len(cameras) if rank == 0 else None, root=0)
        if size == 1:
            link = LocalLink()
            out: dict = {}

            def client_main():
                try:
                    out["records"], out["gl"] = self._client(link, 0, nframes, cfg, clients)
                except BaseException as e:  # noqa: BLE001 - handed to the server loop
                    link.images.put(e)

            th = threading.Thread(target=client_main, name="massview-dmmr-client", daemon=True)
            th.start()
            records, diffs = self._serve(link, cameras, cfg, clients, sink)
            th.join()
            self._client_gl = out.get("gl")
            return records + out.get("records", []), diffs
        rc = split_roles(comm, ROLES)  # rank 0: the server; the others: clients 0 .. N-2
        link = MpiLink(rc)
        out = run_roles(rc, {"server": lambda rc: self._serve(link, cameras, cfg, clients, sink),
                             "client": lambda rc: (self._client(link, rc.role_rank, nframes, cfg, clients), None)})
        gathered = comm.gather(out[0] if rc.role == "client" else None, root=0)
        if rc.role != "server":
            return None
        records, diffs = out
        gl = set()
        for part in gathered:
            if part:
                records.extend(part[0])
                gl.add(part[1])
        self._client_gl = ", ".join(sorted(g for g in gl if g)) or None
        return records, diffs

    def _client(self, link, index: int, nframes: int, cfg: RenderConfig, clients: int) -> tuple[list[dict], str | None]:
        """One client's frames; returns its records and its GL renderer string."""
        client = DmmrClient(self.store, cfg, index, self.ram_budget(clients))
        delay = _delays(cfg)
        tint = rank_tint(index) if cfg.color_by_rank else (0.0, 0.0, 0.0, 0.0)
        records: list[dict] = []
        meter = ProcessMeter()  # per frame: CPU and bytes read of this process (both threads)

        def visibility(f, _):
            task = link.recv_task()
            stats = FrameStats(frame=f, rank=index + 1)
            time.sleep(delay.get("visibility", 0.0))
            v = client.visibility(task, stats)
            if f == nframes - 1:
                client.release_visibility()
            return v

        def render(f, v):
            time.sleep(delay.get("render", 0.0))
            _, payload = client.render(v, v.stats, tint)
            with v.stats.stage("send"):
                link.send_image(payload)
            v.stats.bytes_sent += len(payload)
            for k, x in meter.step().items():
                v.stats.count(k, x)
            records.append({**v.stats.to_json(), **v.ids})
            if f == nframes - 1:
                client.release_render()

        try:
            StagePipeline([("visibility", visibility), ("render", render)], pipelined=cfg.stage_pipeline == "on").run(range(nframes))
            link.flush()
            gl = client.gl_renderer()
        finally:
            client.close()
        return records, gl

    def _divide_send(self, f: int, cam: Camera, clients: int, link, delay: float = 0.0) -> tuple:
        """Server module 1 for frame ``f``: divide, then send each client its task."""
        st = FrameStats(frame=f, rank=0)
        t0 = time.perf_counter()
        with st.stage("divide"):
            tasks, vis, lv = self.server.divide(f, cam, clients)
            time.sleep(delay)
        with st.stage("send"):
            for c, t in enumerate(tasks):
                link.send_task(c, t)
        return t0, st, tasks, vis, lv

    def _assemble(self, cam: Camera, clients: int, link, st: FrameStats) -> Image:
        """Server module 4: receive, decompress and paste every client's sub-frame."""
        full = blank_image(cam.viewport)
        t_a = 0.0
        for c in range(clients):
            buf = link.recv_image(c)
            t1 = time.perf_counter()
            full.paste(decode_image(buf))
            t_a += time.perf_counter() - t1
            st.bytes_recv += buf.size + 8
        st.times_ms["assemble"] = t_a * 1e3
        return full

    def _finish(self, f, cam, cfg, frame: tuple, full: Image, sink) -> tuple[FrameStats, tuple | None]:
        t0, st, tasks, vis, lv = frame
        st.count("objects_in_frustum", len(vis))
        st.count("objects_sent", sum(len(t.items) for t in tasks))
        st.count("triangles_in_frustum", int(self.server.tris[vis, lv].sum()))
        st.count("latency_ms", (time.perf_counter() - t0) * 1e3)
        if sink is not None:
            sink(f, full)
        diff = image_diff(full, self.render_reference(cam, vis, lv)) if cfg.reference else None
        return st, diff

    def _serve(self, link, cameras, cfg: RenderConfig, clients: int, sink) -> tuple[list[dict], list]:
        """The server: a division thread (at most 3 frames ahead when pipelined) and assembly."""
        credits = threading.Semaphore(3 if cfg.stage_pipeline == "on" else 1)
        sent = [threading.Event() for _ in cameras]
        frames: dict[int, tuple] = {}
        delay = _delays(cfg).get("divide", 0.0)

        def divider():
            try:
                for f, cam in enumerate(cameras):
                    credits.acquire()
                    frames[f] = self._divide_send(f, cam, clients, link, delay)
                    sent[f].set()
            except BaseException as e:  # noqa: BLE001 - ends every rank
                link.fail(e)

        th = threading.Thread(target=divider, name="massview-dmmr-divide", daemon=True)
        th.start()
        records, diffs = [], []
        meter = ProcessMeter()
        writer = SinkThread(sink) if sink is not None else None  # PNGs are written off the frame period
        with writer or contextlib.nullcontext():
            self._assembly_loop(link, cameras, cfg, clients, writer, credits, sent, frames, records, diffs, meter)
        th.join()
        link.flush()
        return records, diffs

    def _assembly_loop(self, link, cameras, cfg, clients, sink, credits, sent, frames, records, diffs, meter) -> None:
        prev = time.perf_counter()
        for f, cam in enumerate(cameras):
            st = FrameStats(frame=f, rank=0)
            full = self._assemble(cam, clients, link, st)
            sent[f].wait()
            frame = frames.pop(f)
            frame[1].count("frames_in_flight", 1 + sum(1 for g in list(frames) if g > f))  # before the next division may start
            credits.release()
            now = time.perf_counter()
            frame[1].times_ms["assemble"], frame[1].bytes_recv = st.times_ms["assemble"], st.bytes_recv
            frame[1].times_ms["total"], prev = (now - prev) * 1e3, now
            st, diff = self._finish(f, cam, cfg, frame, full, sink)
            if diff is not None:
                diffs.append((f, diff))
            for k, x in meter.step().items():
                st.count(k, x)
            records.append(st.to_json())
            if self._on_record is not None:
                self._on_record(records[-1])

    # -- one frame at a time (the viewer, and any caller of render_frame) ----------------
    def setup(self, comm) -> None:
        """Split the ranks into the server and the clients (collective over ``comm``)."""
        self._comm = comm
        if comm.Get_size() == 1:
            self._link, self._role, self._index, self._clients = LocalLink(), "both", 0, 1
        else:
            rc = split_roles(comm, ROLES)
            self._link, self._role, self._index, self._clients = MpiLink(rc), rc.role, rc.role_rank, comm.Get_size() - 1
        self._client_obj = None

    def render_frame(self, comm, cfg: RenderConfig, camera: Camera | None, frame: int, sink=None):
        """One synchronous frame on every rank of ``comm`` (camera on rank 0): divide, cull,
        render, assemble. Returns a :class:`~massview.systems.frameloop.FrameResult`."""
        from .frameloop import FrameResult

        if getattr(self, "_comm", None) is not comm:
            self.setup(comm)
        link, role = self._link, self._role
        if role in ("server", "both"):
            t0 = time.perf_counter()
            self.server.layout, self.server.grid = self._layout(cfg), cfg.grid  # the viewer may switch it between frames
            fr = self._divide_send(frame, camera, self._clients, link)
            self._split = [t.viewport for t in fr[2]]
        if role in ("client", "both"):
            if self._client_obj is None:
                self._client_obj = DmmrClient(self.store, cfg, self._index, self.ram_budget(self._clients))
            cst = FrameStats(frame=frame, rank=self._index + 1)
            v = self._client_obj.visibility(link.recv_task(), cst)
            _, payload = self._client_obj.render(v, cst, rank_tint(self._index) if cfg.color_by_rank else (0.0, 0.0, 0.0, 0.0))
            with cst.stage("send"):
                link.send_image(payload)
            cst.bytes_sent += len(payload)
            if role == "client":
                return FrameResult(cst, None)
            self._panel_clients = [{**cst.to_json(), "rank": 1}]
        full = self._assemble(camera, self._clients, link, fr[1])
        fr[1].times_ms["total"] = (time.perf_counter() - t0) * 1e3
        st, diff = self._finish(frame, camera, cfg, fr, full, sink)
        return FrameResult(st, full, diff)

    def panel(self, records: list[dict]) -> dict:
        """The viewer panel's M1 table for one frame's gathered records (rank 0 first): the
        viewer's generic ``{title, columns, rows}`` form, one row per figure (values per client)."""
        server = next((r for r in records if r["rank"] == 0), {})
        clients = sorted((r for r in records if r["rank"] > 0), key=lambda r: r["rank"]) or getattr(self, "_panel_clients", [])
        rows = panel_rows(server, clients)
        if self._split:
            rows["split"] = "Algorithm 1" if self.server.layout == "balanced" else f"equal tiles ({self.server.layout})"
            rows["sub-frusta x,y,w,h per client"] = " / ".join(f"{v.x},{v.y},{v.w},{v.h}" for v in self._split)
        return {"title": "M1 (dmmr), per client", "columns": ["figure", "value"], "rows": [[k, v] for k, v in rows.items()]}

    # -- the one-rank reference ---------------------------------------------------------
    def render_reference(self, camera: Camera, vis: np.ndarray | None = None, lv: np.ndarray | None = None) -> Image:
        """Every object in the frustum at the chosen levels, no occlusion culling, one rank."""
        if vis is None:
            vis, lv = self.server.cut(camera)
        if self._ref is None:
            total = int(np.asarray(self.store.skeleton.level_bytes, np.int64).sum())
            ram = BlockCache(packed_loader(self.store), 2 * total + (64 << 20), workers=2)
            self._ref = SceneDrawer(self.store.skeleton, ram, max(self.cfg.gpu_mb << 20, 2 * total + (64 << 20)), self.cfg.egl_device)
        d = self._ref
        with d.ctx:
            d.ensure(vis, lv)
            return d.view.render(camera, camera.viewport, d.draw_fn(camera, vis, lv), FrameStats(-1, 0))

    def close(self) -> None:
        if getattr(self, "_link", None) is not None:
            self._link.flush()
        if getattr(self, "_client_obj", None) is not None:
            self._client_obj.close()
            self._client_obj = None
        if self._ref is not None:
            ram = self._ref.cache.ram
            self._ref.release()
            ram.close()
            self._ref = None
