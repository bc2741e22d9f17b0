"""T2: parallel Röttger simplification for height fields (Gouranton, Limet, Madougou, Melin).

Two roles (:mod:`massview.parallel.roles`): visualization ranks (parent ranks 0 .. V-1, one
per display tile) and C computation ranks (the last C ranks). The paper's pseudo-code (§3):

    computation rank                          visualization rank
    get local data (once: setup)              broadcast view point and frustum
    loop: get view point and frusta           loop: get rendering data
          perform LOD (Röttger, portion)            draw the subscene
          for each visualization rank v             assemble tiles / write wall tile
              cull fans against v's frustum
              send v what changed

* **Data** (setup): the computation leader reads each layer's metadata and sends it to every
  rank; each computation rank then reads only its portion (:class:`LayerPortion`): the exact
  Morton partition by default, so the union of the ranks' triangulations is the serial one.
  Where the colour map is ``auto`` or ``ortho`` and a store holds an orthophoto, the leader
  also sends each visualization rank one level of it to drape (:meth:`_share_drapes`).
* **Frame**: the visualization leader broadcasts the camera; every rank derives the
  visualization tiles and their sub-frusta. Computation ranks optionally agree on the desired
  resolution c under ``--triangle-budget`` (bisection, one Allreduce of one integer per step
  among computation ranks only), run the LOD, cull with bounding spheres per tile, encode
  (index, height) fans with only the changes (:mod:`massview.lod.fanstream`) and send them;
  one ``alltoall`` of message sizes lets a tile that sees nothing of a portion get 0 bytes.
* **Draw**: visualization ranks keep what they hold from each computation rank, draw all
  fans in the canonical (layer, Morton) order — the serial reference's order — and assemble
  the sort-first tiles on visualization rank 0 (or write their own wall tile), whose
  background pixels then get T1's sky (:func:`paint_sky`).
"""

from __future__ import annotations

import time

import numpy as np

from ..core.camera import Camera, Viewport
from ..core.config import RenderConfig
from ..core.errors import ConfigError
from ..core.stats import FrameStats
from ..lod.cull import spheres_in_frustum
from ..lod.fanstream import FanReceiver, FanSender
from ..lod.roettger import RoettgerParams, default_c, partition_depth, portion_nodes, portion_owner
from ..parallel.composite import deliver
from ..render.colormaps import DRAPE_COLORMAPS, Shading, paint_sky
from ..parallel.decompose import parse_wall, sort_first_tiles
from ..parallel.roles import Role, recv_bytes, send_bytes, split_roles
from .frameloop import FrameResult, image_diff
from .roettger_draw import FanDrawer, gather_layers
from .roettger_paper import PaperPortion, paper_layout
from .roettger_portion import LayerInfo, LayerPortion

__all__ = ["RoettgerSystem", "validate", "roles"]

_TAG = 300
_TAG_DRAPE = 310  # (and 311) the orthophoto images of setup
_LAYER_GAP = 1.25  # further layers are drawn this many first-layer height spans below the previous


def roles(cfg: RenderConfig) -> tuple[Role, Role]:
    return (Role("visualization", None, minimum=1), Role("computation", cfg.compute_ranks))


def validate(scene: str, cfg: RenderConfig, nranks: int) -> None:
    """Cheap checks before any rank starts (the rank split, the wall, the stores' tables)."""
    from ..parallel.roles import assign_roles

    if nranks <= cfg.compute_ranks:
        raise ConfigError(f"--compute-ranks {cfg.compute_ranks} leaves no visualization rank among {nranks} ranks; "
                          f"run with --ranks {cfg.compute_ranks + 1} or more")
    assign_roles(roles(cfg), nranks)
    vis = nranks - cfg.compute_ranks
    if cfg.wall:
        c, r = (int(v) for v in cfg.wall.lower().split("x"))
        if c * r != vis:
            raise ConfigError(f"--wall {cfg.wall} needs {c * r} visualization ranks (one per tile); the run has {vis} "
                              f"(--ranks {nranks} minus --compute-ranks {cfg.compute_ranks})")
    if cfg.roettger_c is not None:
        RoettgerParams(c=cfg.roettger_c)  # (walk8 L1: a negative c failed only inside the ranks, under MPI_Abort)
    infos = []
    for spec in (scene, *cfg.layers):
        info = LayerInfo.of(spec)  # a missing store or table fails here with its message
        infos.append(info)
        if cfg.roettger_C is not None:
            RoettgerParams(C=cfg.roettger_C)  # the proven range
            if cfg.roettger_C < info.C_min:
                raise ConfigError(f"--roettger-C {cfg.roettger_C:g} is below the C_min {info.C_min:g} the table of {spec} was "
                                  f"propagated for; use --roettger-C >= {info.C_min:g} or re-run "
                                  f"`massview prepare roettger {spec} --min-C {cfg.roettger_C:g}`")
    depth0 = _partition_depth(cfg.compute_ranks, infos)
    for spec, info in zip((scene, *cfg.layers), infos):
        if depth0 > info.n - 1:
            raise ConfigError(f"{spec} is too small for {cfg.compute_ranks} computation ranks (partition depth {depth0}, its "
                              f"quadtree has {info.n} levels); use fewer --compute-ranks")


def data_extent(infos) -> tuple[float, float]:
    """The fractions (rows, cols) of the padded square that hold data, over all layers: the
    portions share the data, not the padding (:func:`massview.lod.roettger.portion_nodes`)."""
    return (max((i.rows - 1) / (i.S - 1) for i in infos), max((i.cols - 1) / (i.S - 1) for i in infos))


def _partition_depth(C: int, infos) -> int:
    """The portions' depth for C computation ranks over the layers ``infos``
    (:func:`massview.lod.roettger.partition_depth` of their data extent, at most the
    shallowest layer's last level)."""
    return partition_depth(C, data_extent(infos), min(i.n for i in infos) - 1)


def _vis_layout(cfg: RenderConfig) -> str:
    """The sort-first layout of the visualization ranks' tiles (horizontal unless
    ``--decomposition sort-first:vertical|grid``)."""
    layout = cfg.decomposition.partition(":")[2] if cfg.decomposition.startswith("sort-first:") else "horizontal"
    return layout if layout in ("horizontal", "vertical", "grid") else "horizontal"


def _vis_tiles(cfg: RenderConfig, nvis: int, width: int, height: int) -> list[Viewport]:
    if cfg.wall:
        return parse_wall(cfg.wall, nvis, width, height)
    return sort_first_tiles(_vis_layout(cfg), nvis, width, height, cfg.grid)


class RoettgerSystem:
    """T2 over one or more terrain stores (layers): :meth:`render_frame` once per frame on
    every rank of the run's communicator (the first call splits the roles and loads the data)."""

    sort_last_modes: tuple[str, ...] = ()

    @staticmethod
    def split_label(cfg: RenderConfig) -> tuple[str, str]:
        """(decomposition, compositor) as the summary names them: visualization ranks draw
        sort-first tiles (or wall tiles) of what the computation ranks send."""
        return (f"wall {cfg.wall}" if cfg.wall else f"sort-first:{_vis_layout(cfg)}"), "tile-assembly"

    work_roles = ("computation",)  # the ranks whose triangles the summary's imbalance compares

    def rank_roles(self, n: int) -> list[str]:
        """Each of the ``n`` ranks' role: visualization first, computation last."""
        from ..parallel.roles import assign_roles

        out = [""] * n
        for name, ranks in assign_roles(roles(self.cfg), n).items():
            for r in ranks:
                out[r] = name
        return out

    def __init__(self, specs, cfg: RenderConfig):
        self.specs = [str(s) for s in specs]
        self.cfg = cfg
        self.rc = None
        self.infos: list[LayerInfo] = []
        self.portions: list[LayerPortion] = []
        self._drawer: FanDrawer | None = None
        self._reference = None

    # -- setup ----------------------------------------------------------------------------
    def layer_infos(self) -> list[LayerInfo]:
        """Each layer's metadata (store attributes only) with its z offset and index grid."""
        cfg = self.cfg
        infos = [LayerInfo.of(s) for s in self.specs]
        Z = float(cfg.exaggeration)
        if Z != 1.0:  # T1's exaggeration, base + Z·(h·vs − base) with base the lowest height: a vertical scale Z·vs
            infos = [LayerInfo(**{**i.__dict__, "vscale": i.vscale * Z, "zoffset": (1.0 - Z) * i.zrange[0] * i.vscale})
                     for i in infos]  # and an offset; the LOD sees it too (d2 is scaled by the vertical scale)
        span = (infos[0].zrange[1] - infos[0].zrange[0]) * infos[0].vscale
        infos = [LayerInfo(**{**i.__dict__, "zoffset": i.zoffset - k * _LAYER_GAP * span}) for k, i in enumerate(infos)]
        if cfg.paper_partition:  # the overlapping portions index vertices in a wider grid
            infos = [LayerInfo(**{**i.__dict__, "dim": paper_layout(i.rows, i.cols, cfg.compute_ranks, i.S)[2]}) for i in infos]
        return infos

    def setup(self, comm) -> None:
        """Split ``comm`` into the two roles and load the data (collective; done by the first
        :meth:`render_frame` when not called before)."""
        cfg = self.cfg
        self.comm = comm
        self.rc = rc = split_roles(comm, roles(cfg))
        self.vis_ranks, self.comp_ranks = rc.ranks["visualization"], rc.ranks["computation"]
        lead = rc.leader("computation")
        self.infos = comm.bcast(self.layer_infos() if comm.Get_rank() == lead else None, root=lead)
        C = cfg.roettger_C if cfg.roettger_C is not None else max(i.C_min for i in self.infos)
        for i in self.infos:
            if C < i.C_min:
                raise ConfigError(f"--roettger-C {C:g} is below the C_min {i.C_min:g} the table of {i.path} was propagated for; "
                                  f"use --roettger-C >= {i.C_min:g} or re-run `massview prepare roettger {i.path} --min-C {C:g}`")
        self.C = C
        self._extent = data_extent(self.infos)
        self.depth0 = _partition_depth(len(self.comp_ranks), self.infos)
        self.bytes_read = 0
        if rc.role == "computation":
            if cfg.paper_partition:
                self.portions = [PaperPortion(i, rc.role_rank, len(self.comp_ranks)) for i in self.infos]
            else:
                nodes = portion_nodes(self.depth0, len(self.comp_ranks), self._extent)[rc.role_rank]
                self.portions = [LayerPortion(i, nodes, self.depth0) for i in self.infos]
            self.bytes_read = sum(p.bytes_read for p in self.portions)
            self.senders = {v: FanSender(len(self.infos)) for v in self.vis_ranks}
        else:
            self._drawer = FanDrawer(self.infos, cfg.egl_device, Shading(cfg.exaggeration, tuple(cfg.sun),
                                                                         cfg.colormap, cfg.haze))
            self.receivers = {c: FanReceiver(len(self.infos)) for c in self.comp_ranks}
        self._share_drapes(comm, lead)
        self._first = True

    def _share_drapes(self, comm, lead: int) -> None:
        """Each layer's orthophoto, where the store has one and the colour map drapes it
        (``auto``, ``ortho``): the computation leader reads one level of it
        (:func:`~massview.data.terrain.drape.drape_level`: at most 4097² texels) and sends it to
        every visualization rank, which drapes it over that layer's fans (visualization ranks
        still never open a store). Collective over ``comm``, in layer order."""
        if self.cfg.colormap not in DRAPE_COLORMAPS or not any(i.color for i in self.infos):
            return
        from ..data.terrain import TerrainStore
        from ..data.terrain.drape import color_image, drape_level

        me = comm.Get_rank()
        for li, info in enumerate(self.infos):
            if not info.color:
                continue
            if me == lead:
                st = TerrainStore(info.path)
                level = drape_level(st.layout)
                img = color_image(st, level)
                self.bytes_read += img.nbytes
                for v in self.vis_ranks:
                    comm.send((level, img.shape), dest=v, tag=_TAG_DRAPE)
                    comm.Send(img, dest=v, tag=_TAG_DRAPE + 1)
            elif me in self.vis_ranks:
                level, shape = comm.recv(source=lead, tag=_TAG_DRAPE)
                img = np.empty(shape, np.uint8)
                comm.Recv(img, source=lead, tag=_TAG_DRAPE + 1)
                self._drawer.fans.set_drape(li, img, level)

    @property
    def bounds(self):
        """World box of all layers (from the stores' attributes when not set up yet)."""
        infos = self.infos or self.layer_infos()
        los, his = zip(*(i.bounds() for i in infos))
        return np.min(los, axis=0), np.max(his, axis=0)

    def ground(self, cfg: RenderConfig | None = None):
        """The surface the ``walkthrough`` path walks on: the highest layer under each point, as
        drawn (height · vertical scale + the layer's z offset)."""
        from ..data.terrain import TerrainStore
        from ..lod.walk import terrain_ground

        grounds = [terrain_ground(TerrainStore(i.path), lambda h, i=i: np.asarray(h, np.float64) * i.vscale + i.zoffset)
                   for i in (self.infos or self.layer_infos())]
        return lambda xy: np.max([g(xy) for g in grounds], axis=0)

    @property
    def renderer(self) -> str:
        return self._drawer.renderer if self._drawer is not None else "computation rank (no GL)"

    def params(self, camera: Camera, c: float | None = None) -> RoettgerParams:
        cfg = self.cfg
        if c is None:
            c = cfg.roettger_c if cfg.roettger_c is not None else default_c(cfg.tau, camera.fovy, camera.height)
        return RoettgerParams(C=self.C, c=c, depth0=self.depth0)

    # -- frame ----------------------------------------------------------------------------
    def render_frame(self, comm, cfg: RenderConfig, camera: Camera | None, frame: int, sink=None) -> FrameResult:
        """One frame on every rank of ``comm`` (``camera`` matters on rank 0, the
        visualization leader); returns this rank's stats and, on display ranks, its tile."""
        if self.rc is None:
            self.setup(comm)
        self.cfg = cfg
        comm, rc = self.comm, self.rc
        stats = FrameStats(frame=frame, rank=comm.Get_rank())
        stats.count("store_bytes_read", self.bytes_read if self._first else 0)
        self._first = False
        with stats.stage("total"):
            camera = self._camera(camera)
            tiles = _vis_tiles(cfg, len(self.vis_ranks), camera.width, camera.height)
            tile, c_used = None, None
            if rc.role == "computation":
                msgs, c_used = self._compute(camera, tiles, stats)
                heads = [comm.isend((len(msgs.get(v, b"")), c_used), dest=v, tag=_TAG + 1) for v in self.vis_ranks]
                reqs = send_bytes(comm, {v: np.frombuffer(m, np.uint8) for v, m in msgs.items() if m}, _TAG)
                with stats.stage("transfer"):
                    _polite_wait(heads + reqs)
            else:
                sizes = {c: _polite_recv(comm, c, _TAG + 1) for c in self.comp_ranks}
                tile, c_used = self._visualize(cfg, camera, tiles, sizes, stats)
        if tile is not None:  # the sky behind the terrain, on the final pixels, as T1 paints it
            with stats.stage("finish"):
                tile = paint_sky(camera, tile)
        result = FrameResult(stats, tile)
        if tile is not None:
            if sink is not None:
                sink(frame, tile)
            if cfg.reference:
                ref = paint_sky(camera, self._reference_image(camera, c_used, stats).crop(tile.viewport))
                result.diff = image_diff(tile, ref)
        self._frame_done()
        return result

    # Waiting. A run often has more ranks than cores (4+1 on 2 cores here); an MPI wait spins
    # a core, taking it from the ranks that work (the LOD, the draw). So T2 waits politely:
    # the camera, the message sizes and the end of the frame travel as small point-to-point
    # messages tested every 0.2 ms (a frame is 100 ms or more), and the run's own collectives
    # (stats gathers) start when every rank is already there.
    def _camera(self, camera: Camera | None) -> Camera:
        """The visualization leader's camera on every rank."""
        comm = self.comm
        if comm.Get_rank() == 0:
            _polite_wait([comm.isend(camera, dest=r, tag=_TAG + 2) for r in range(1, comm.Get_size())])
            return camera
        return _polite_recv(comm, 0, _TAG + 2)

    def _frame_done(self) -> None:
        """Computation ranks wait (politely) until the visualization leader has finished the frame."""
        comm = self.comm
        if comm.Get_rank() == 0:
            _polite_wait([comm.isend(None, dest=c, tag=_TAG + 3) for c in self.comp_ranks])
        elif self.rc.role == "computation":
            _polite_recv(comm, 0, _TAG + 3)

    def _compute(self, camera: Camera, tiles: list[Viewport], stats: FrameStats) -> tuple[dict, float]:
        cfg = self.cfg
        planes = [camera.frustum_planes(vp) for vp in tiles]
        params = self.params(camera)
        if cfg.triangle_budget is not None:
            with stats.stage("budget"):
                params = self._budget(camera, params, planes, cfg.triangle_budget, stats)
        with stats.stage("lod"):
            layers = []
            for p in self.portions:
                leaves = p.select(camera.position, params)
                fans, heights = p.fans(leaves)
                layers.append((fans, heights))
        stats.count("fans", sum(len(f) for f, _ in layers))
        msgs, seen_any = {}, 0
        with stats.stage("cull"):
            vis = [[spheres_in_frustum(f.sphere[:, :3], f.sphere[:, 3], pl) for f, _ in layers] for pl in planes]
        with stats.stage("encode"):
            for v, rank in enumerate(self.vis_ranks):
                sec = []
                for (f, h), sel in zip(layers, vis[v]):
                    part = f.take(sel)
                    hv = h[np.repeat(sel, f.lengths.astype(np.int64))]
                    sec.append((part.centre * 16 + part.mask, part.lengths, part.index, hv))
                msg, st = self.senders[rank].encode(sec, delta=cfg.fan_delta)
                if st.fans == 0 and all(len(s) == 0 for s in self.senders[rank].held) and _empty(msg):
                    msg = b""
                msgs[rank] = msg
                stats.bytes_sent += len(msg)
                stats.count(f"bytes_to_vis_{v}", len(msg))
                stats.count("bytes_full", st.full)
                stats.count("bytes_xyz", st.xyz)
                stats.count("new_fans", st.new_fans)
            for (f, _), sels in zip(layers, zip(*vis)):
                seen_any += f.take(np.logical_or.reduce(sels)).triangles()
        stats.count("fan_triangles", seen_any)
        stats.triangles = seen_any  # T2's triangles are produced here (see _visualize)
        stats.count("roettger_c", params.c)
        return msgs, params.c

    def _budget(self, camera: Camera, params: RoettgerParams, planes, budget: int, stats: FrameStats) -> RoettgerParams:
        """The largest c (≤ the configured one) whose visible triangle total is ≤ budget, found
        by bisection; each step sums the ranks' counts with one Allreduce (computation ranks)."""
        def total(c: float) -> int:
            p = RoettgerParams(params.C, c, params.depth0)
            n = 0
            for portion in self.portions:
                fans, _ = portion.fans(portion.select(camera.position, p))
                seen = np.logical_or.reduce([spheres_in_frustum(fans.sphere[:, :3], fans.sphere[:, 3], pl) for pl in planes])
                n += fans.take(seen).triangles()
            stats.count("budget_steps", 1)
            return int(self.rc.comm.allreduce(n))

        hi, n_hi = params.c, total(params.c)
        if n_hi <= budget:
            return params
        lo, best = 0.0, 0.0
        if total(0.0) > budget:
            stats.count("budget_unreachable", 1)
            return RoettgerParams(params.C, 0.0, params.depth0)
        for _ in range(48):
            mid = (lo + hi) / 2 if lo == 0.0 and hi < 1e-9 else (np.sqrt(lo * hi) if lo > 0 else hi / 16)
            n = total(mid)
            if n <= budget:
                lo, best = mid, mid
                if n >= 0.9 * budget:
                    break
            else:
                hi = mid
        return RoettgerParams(params.C, best, params.depth0)

    def _visualize(self, cfg: RenderConfig, camera: Camera, tiles: list[Viewport], sizes, stats: FrameStats):
        rc = self.rc
        v = rc.role_rank
        with stats.stage("transfer"):
            got = recv_bytes(self.comm, [c for c in self.comp_ranks if sizes[c][0] > 0], _TAG)
        c_used = sizes[self.comp_ranks[0]][1]
        for c in self.comp_ranks:
            msg = got.get(c)
            stats.bytes_recv += 0 if msg is None else len(msg)
            self.receivers[c].apply(msg if msg is not None else None)
        vp = tiles[v]
        layers = gather_layers([self.receivers[c].held for c in self.comp_ranks], self.infos)
        image = self._drawer.draw(camera, vp, layers, cfg.color_by_rank, stats)
        # A frame's triangles are counted once, by the computation rank that produced them
        # (``triangles`` per rank is the LOD's load; the run's sum is the scene's count, as in
        # T1); what this rank drew is ``drawn_triangles``.
        stats.count("drawn_triangles", stats.triangles)
        stats.triangles = 0
        if cfg.wall:
            return image, c_used
        return deliver(rc.comm, image, [(0, camera.viewport)], stats, cfg.codec), c_used

    # -- reference ------------------------------------------------------------------------
    def _reference_image(self, camera: Camera, c: float, stats: FrameStats):
        """The serial image: one rank runs the whole-DEM LOD (all portions) alone and draws
        every fan (no culling: the paper's sequential version). Its LOD time is recorded as
        ``reference_lod_ms`` (the sequential baseline of §4.1), LOD + draw as ``reference_ms``
        (Figure 6's sequential frame), both measured while the computation ranks sleep."""
        if self._reference is None:
            N = 2**self.depth0
            every = np.stack(np.meshgrid(np.arange(N), np.arange(N), indexing="ij"), -1).reshape(-1, 2)
            self._reference = [LayerPortion(i, every, self.depth0) for i in self.infos]
            self._owner = portion_owner(self.depth0, len(self.comp_ranks), self._extent)
        params = self.params(camera, c)
        t0 = time.perf_counter()
        out = [p.fans(p.select(camera.position, params)) for p in self._reference]  # Morton order of the whole DEM
        stats.count("reference_lod_ms", (time.perf_counter() - t0) * 1e3)
        layers = []
        for p, (fans, h) in zip(self._reference, out):
            shift = p.n - self.depth0
            row, col = fans.centre // p.info.index_dim, fans.centre % p.info.index_dim
            layers.append((fans.lengths, fans.index, h, self._owner[row >> shift, col >> shift]))
        image = self._drawer.draw(camera, camera.viewport, layers, self.cfg.color_by_rank, FrameStats(-1, 0))
        stats.count("reference_ms", (time.perf_counter() - t0) * 1e3)
        return image

    def panel(self, records: list[dict]) -> dict:
        """Per-rank figures of one frame for the viewer's panel (``records``: every rank's
        FrameStats JSON): a table of strings, one row per rank."""
        rows = []
        V = len(self.vis_ranks)
        for r in sorted(records, key=lambda r: r["rank"]):
            c, t = r["counters"], r["times_ms"]
            if r["rank"] in self.comp_ranks:
                sent = ", ".join(_kb(c.get(f"bytes_to_vis_{v}", 0)) for v in range(V))
                rows.append([str(r["rank"]), "computation", f"{t.get('lod', 0):.1f}", f"{c.get('fans', 0):.0f}",
                             f"{r['triangles'] / 1e3:.1f}k", f"to vis {sent}"])
            else:
                rows.append([str(r["rank"]), "visualization", f"draw {t.get('draw', 0):.1f}", "",
                             f"drew {c.get('drawn_triangles', 0) / 1e3:.1f}k", f"got {_kb(r['bytes_recv'])}"])
        return {"title": "T2 per rank", "columns": ["rank", "role", "LOD ms", "fans", "triangles", "bytes"], "rows": rows}

    def close(self) -> None:
        if self._drawer is not None:
            self._drawer.release()


def _polite_wait(reqs: list) -> None:
    """Complete requests, sleeping 0.2 ms between tests instead of spinning."""
    pending = list(reqs)
    while pending:
        pending = [r for r in pending if not r.Test()]
        if pending:
            time.sleep(2e-4)


def _polite_recv(comm, source: int, tag: int):
    """A small pickled message from ``source``, received without spinning."""
    req = comm.irecv(source=source, tag=tag)
    while True:
        done, value = req.test()
        if done:
            return value
        time.sleep(2e-4)


def _kb(n: float) -> str:
    return f"{n / 1e3:.1f} kB"


def _empty(msg: bytes) -> bool:
    """A message that keeps nothing and adds nothing (n_prev = n_new = 0 in every layer)."""
    a = np.frombuffer(msg, "<u4")
    return bool(np.all(a[1:] == 0))

