"""M2 — asynchronous Reliefboards computed by backend ranks (Süß et al. 2010).

Two roles (:mod:`~massview.parallel.roles`): one **visualization rank** (the parent's rank 0)
and the **backends** (all other ranks); messages between them go over the parent communicator.
Object data are placed on the backends at random with a fixed number of replicas (§6.2); every
rank derives the same placement from the seed.

Visualization rank, each frame (§6.1):

1. **receive** — boards that arrived completely replace the objects' old boards;
2. **plan** — infeasible objects and the near zone (front to back until t_nz) as originals; far
   objects from their board if its angle error is below E, else as originals; requests for far
   objects without a board, past ε, or past the size threshold, never two pending per object
   (:func:`~massview.lod.boardpolicy.plan_frame`);
3. **draw** — originals with the mesh renderer, boards lit like them where they were created;
4. **request** — the new requests go to replica holders by the modified c-collision protocol
   (:func:`~massview.parallel.ccollision.assign_requests`) and leave with non-blocking sends.

The visualization rank builds no board itself and never waits for a backend: its frame loop
uses only ``isend``/``Improbe``/``Irecv``/``Test`` (:mod:`~massview.parallel.boardlink`) and
no collective. Backends build boards in the order requested (§5, four render passes) and send
them back. ``stall_backend`` makes one backend hold every request until the run ends (or adds a
delay per board) to show that only its own requests wait.

Per-frame metrics (§7) are :class:`FrameStats` counters on the visualization rank.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..core.camera import Camera
from ..core.errors import ConfigError, ParallelError
from ..core.image import Image
from ..core.stats import FrameStats
from ..lod.boardpolicy import BoardPolicy, plan_frame
from ..lod.clusters import ClusterParams
from ..lod.cull import spheres_in_frustum
from ..lod.reliefboard import decode_board, encode_board
from ..parallel.boardlink import BoardRequest, BackendLink, VisualizationLink
from ..parallel.ccollision import assign_requests, place_replicas
from ..parallel.roles import Role, assign_roles, split_roles
from ..render.boards import BoardBuilder, BoardRenderer
from ..render.context import create_context, renderer_string
from ..render.meshes import MeshRenderer, rank_tint
from ..render.view import ViewRenderer
from .boardscene import BoardObjects

__all__ = ["ReliefboardOptions", "VisualizationRank", "BackendRank", "ROLES", "run_reliefboards"]

ROLES = (Role("visualization", 1), Role("backend", None, minimum=1))


@dataclass(frozen=True)
class ReliefboardOptions:
    """M2 parameters. ``policy``: the §6.1 parameters (ε, E, size threshold, t_nz, p) with the
    paper's defaults, t_nz scaled to this machine (:mod:`massview.lod.boardpolicy`, the one
    place they are declared); ``replicas`` per object and the ``seed`` of their placement;
    ``min_triangles`` (None: 2·p²); ``stall_backend`` (rank, or None) and ``stall_s`` (None:
    stalled for the whole run; else seconds added per board); ``tie_rule``: "pending" (an
    assignment persists until its board arrives and counts as load, :mod:`ccollision`),
    "frame" (only this frame's assignments count) or "run" (every assignment of the run counts:
    not the issue's "in the frame", but the one that evens out single-request frames); ``wait_boards``: the visualization rank
    waits at the start of each frame until every pending board has arrived — a deterministic
    mode for the API/CLI comparison and references only, never the system's behaviour;
    ``reference_every``: with ``--reference``, draw the all-original reference every k-th frame
    only (benchmarks: the baseline costs several boards frames)."""

    policy: BoardPolicy = field(default_factory=BoardPolicy)
    replicas: int = 3
    seed: int = 0
    min_triangles: int | None = None
    stall_backend: int | None = None
    stall_s: float | None = None
    tie_rule: str = "pending"
    wait_boards: bool = False
    reference_every: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.policy, BoardPolicy):
            raise ConfigError(f"policy must be a massview.lod.boardpolicy.BoardPolicy, got {type(self.policy).__name__}")
        if self.replicas < 1:
            raise ConfigError(f"--replicas must be at least 1, got {self.replicas}")
        if self.stall_s is not None and self.stall_s < 0:
            raise ConfigError(f"--stall-backend delay must be non-negative, got {self.stall_s}")
        if self.reference_every < 1:
            raise ConfigError(f"--reference-every must be at least 1, got {self.reference_every}")
        if self.tie_rule not in ("pending", "frame", "run"):
            raise ConfigError(f"--tie-rule must be pending, frame or run, got {self.tie_rule!r}")
        if self.wait_boards and self.stall_backend is not None and self.stall_s is None:
            raise ConfigError("--wait-boards with a backend stalled for the whole run would never finish; give --stall-backend RANK:SECONDS")

    @property
    def t_nz(self) -> int:
        return self.policy.t_nz

    @property
    def p(self) -> int:
        return self.policy.p

    def cluster_params(self, height: int, fovy: float) -> ClusterParams:
        return ClusterParams(t_nz=max(1, self.t_nz), p=self.p, r_y=height, fovy=fovy, min_triangles=self.min_triangles)


class VisualizationRank:
    """Rank 0's state: resident boards, pending requests, the object data for originals."""

    def __init__(self, comm, backends: list[int], objects: BoardObjects, opts: ReliefboardOptions, egl_device=None,
                 tint_boards=False):
        if not backends:
            raise ConfigError("the reliefboards system needs at least one backend: run with --ranks 2 or more")
        self.obj, self.opts, self.policy = objects, opts, opts.policy
        self.backends = list(backends)
        self.holders = place_replicas(objects.count, len(self.backends), opts.replicas, opts.seed)
        self.link = VisualizationLink(comm, self.backends)
        self.ctx = create_context(egl_device)
        self.renderer = renderer_string(self.ctx)
        self.meshes = MeshRenderer(self.ctx, *objects.concatenated())
        self.boards = BoardRenderer(self.ctx)
        self.view = ViewRenderer(self.ctx)
        n = objects.count
        self.board_dir = np.full((n, 3), np.nan)
        self.board_size = np.zeros(n, np.int64)
        self.board_from = np.full(n, -1, np.int64)
        self.pending = np.zeros(n, bool)
        self.pending_to = np.full(n, -1, np.int64)
        self.pending_since = np.zeros(n)
        self.serial = 0
        self.assigned = np.zeros(len(self.backends), np.int64)  # requests assigned per backend over the run
        self.tint_boards = tint_boards
        self.centers, self.radii = objects.centers, objects.radii

    # -- the frame ------------------------------------------------------------------------
    def frame(self, camera: Camera, f: int) -> tuple[Image, FrameStats]:
        stats = FrameStats(frame=f, rank=0)
        with stats.stage("total"):
            with stats.stage("transfer"):
                self._receive(stats)
            with stats.stage("lod"):
                plan = plan_frame(camera, self.centers, self.radii, self.obj.triangles, self.obj.feasible,
                                  self.board_dir, self.board_size, self.pending, self.policy)
            image = self.view.render(camera, camera.viewport, lambda mvp: self._draw(plan, mvp), stats)
            with stats.stage("encode"):
                self._request(plan, stats)
        self._record(plan, stats)
        return image, stats

    def _receive(self, stats: FrameStats) -> None:
        got = self.link.poll()
        while self.opts.wait_boards and len(got) < int(self.pending.sum()):  # deterministic mode only
            time.sleep(0.001)
            got += self.link.poll()
        now = time.perf_counter()
        for src, data in got:
            board = decode_board(data)
            oid = board.object_id
            if self.pending_to[oid] != src:
                raise ParallelError(f"backend {src} answered object {oid}, which it was not asked for")
            self.boards.put(board)
            self.board_dir[oid] = board.frame.direction
            self.board_size[oid] = board.frame.size
            self.board_from[oid] = src
            self.pending[oid] = False
            self.pending_to[oid] = -1
            stats.count("answered")
            stats.counters.setdefault("response_ms", []).append(round((now - self.pending_since[oid]) * 1e3, 3))
            stats.bytes_recv += len(data)

    def _draw(self, plan, mvp) -> int:
        originals = np.sort(np.concatenate([plan.infeasible, plan.near, plan.far_original]))
        tris = self.meshes.draw(originals, mvp)
        if not self.tint_boards:
            return tris + self.boards.draw(plan.far_board, mvp)
        for b in np.unique(self.board_from[plan.far_board]):
            ids = plan.far_board[self.board_from[plan.far_board] == b]
            tris += self.boards.draw(ids, mvp, rank_tint(int(b)))
        return tris

    def _request(self, plan, stats: FrameStats) -> None:
        if len(plan.requests) == 0:
            stats.counters["loads"] = [0] * len(self.backends)
            return
        prior = {"pending": self._pending_by_backend(), "run": self.assigned, "frame": None}[self.opts.tie_rule]
        a = assign_requests(plan.requests, self.holders, len(self.backends), prior)
        self.assigned += a.loads
        now = time.perf_counter()
        for oid, d, s, b in zip(plan.requests, plan.request_dirs, plan.request_sizes, a.backend):
            rank = self.backends[int(b)]
            self.link.send(rank, BoardRequest(int(oid), tuple(float(v) for v in d), int(s), self.serial))
            self.serial += 1
            self.pending[oid], self.pending_to[oid], self.pending_since[oid] = True, rank, now
        stats.count("requests", len(plan.requests))
        stats.counters["loads"] = a.loads.tolist()
        stats.counters["c_rounds"] = a.rounds

    def _pending_by_backend(self) -> np.ndarray:
        """int64 (n_backends,) requests assigned and not yet answered, per backend index."""
        index = np.searchsorted(self.backends, self.pending_to[self.pending])
        return np.bincount(index, minlength=len(self.backends)).astype(np.int64)

    def _record(self, plan, stats: FrameStats) -> None:
        t = self.obj.triangles
        stats.counters["tris_near"] = int(plan.near_triangles)
        stats.counters["tris_far_original"] = int(t[plan.far_original].sum())
        stats.counters["tris_board"] = int(sum(self.boards.triangles(i) for i in plan.far_board))
        stats.counters["boards_drawn"] = len(plan.far_board)
        stats.counters["far_original"] = len(plan.far_original)
        stats.counters["pending"] = int(self.pending.sum())
        stats.counters["pending_by_backend"] = self._pending_by_backend().tolist()
        stats.counters["angle_error"] = np.round(plan.angle_error, 3).tolist()
        far = np.concatenate([plan.far_original, plan.far_board])
        stats.counters["far_objects"] = len(far)
        # complete: every far object drawn as a board, none waiting for one; a frame with no far object proves
        # nothing (walk6 #8: "complete view after 60 ms" on a hall whose flyover never had one)
        stats.counters["view_complete"] = int(len(far) > 0 and len(plan.far_original) == 0 and not self.pending[far].any())
        stats.counters["board_passes_here"] = BoardBuilder.process_passes
        stats.bytes_sent = self.link.bytes_sent
        self.link.bytes_sent = 0

    def render_reference(self, camera: Camera, stats: FrameStats | None = None) -> Image:
        """Every object in the frustum with its original geometry (the --reference oracle and
        the all-original baseline frame time, recorded in ``stats``)."""
        vis = np.nonzero(spheres_in_frustum(self.centers, self.radii, camera.frustum_planes()))[0]
        stats = stats if stats is not None else FrameStats(frame=-1, rank=0)
        return self.view.render(camera, camera.viewport, lambda mvp: self.meshes.draw(vis, mvp), stats)

    def close(self) -> int:
        """Stop the backends and drain their last boards; returns how many arrived late."""
        late = self.link.close()
        self.view.release()
        self.boards.release()
        self.meshes.release()
        return len(late)


class BackendRank:
    """A backend: builds the boards it is asked for, in order, from its replicas."""

    def __init__(self, comm, viz: int, backends: list[int], objects: BoardObjects, opts: ReliefboardOptions, egl_device=None):
        self.rank = comm.Get_rank()
        self.obj, self.opts = objects, opts
        holders = place_replicas(objects.count, len(backends), opts.replicas, opts.seed)
        self.held = np.any(holders == backends.index(self.rank), axis=1)
        self.link = BackendLink(comm, viz)
        self.ctx = create_context(egl_device)
        self.builder = BoardBuilder(self.ctx)
        self.stalled = opts.stall_backend == self.rank
        self.built, self.build_ms = 0, []
        self._meshes: dict[int, tuple] = {}  # the replicas this backend holds, loaded on first request

    def _build(self, req: BoardRequest) -> bytes:
        if not self.held[req.object_id]:
            raise ConfigError(f"backend {self.rank} was asked for object {req.object_id}, of which it holds no replica")
        t0 = time.perf_counter()
        mesh = self._meshes.get(req.object_id)
        if mesh is None:
            mesh = self._meshes[req.object_id] = self.obj.mesh(req.object_id)
        board = self.builder.build(req.object_id, *mesh, direction=req.direction, size=req.size,
                                   box_lo=self.obj.box_lo[req.object_id], box_hi=self.obj.box_hi[req.object_id],
                                   origin=self.obj.origins[req.object_id])
        data = encode_board(board)
        self.build_ms.append((time.perf_counter() - t0) * 1e3)
        self.built += 1
        return data

    def run(self) -> dict:
        """Serve requests until STOP; returns this backend's counters."""
        queue: deque[BoardRequest] = deque()
        received = 0
        while not self.link.stopped:
            got = self.link.requests()
            received += len(got)
            queue.extend(got)
            if self.link.stopped:
                break
            if not queue or (self.stalled and self.opts.stall_s is None):
                time.sleep(0.002)
                continue
            if self.stalled:
                time.sleep(self.opts.stall_s)
            self.link.send_board(self._build(queue.popleft()))
        self.link.close()
        self.builder.release()
        return {"rank": self.rank, "received": received, "built": self.built, "unserved": len(queue),
                "build_ms_mean": float(np.mean(self.build_ms)) if self.build_ms else 0.0,
                "objects_held": int(self.held.sum())}


def check_stall(opts: ReliefboardOptions, nranks: int) -> None:
    """``--stall-backend RANK`` must name a backend of an ``nranks`` job: a ConfigError naming
    them where not (before the job starts, so it is said once, not by every rank)."""
    if opts.stall_backend is None:
        return
    backends = assign_roles(ROLES, nranks)["backend"]
    if opts.stall_backend not in backends:
        which = f"rank {backends[0]}" if len(backends) == 1 else f"ranks {backends[0]}..{backends[-1]}"
        raise ConfigError(f"--stall-backend {opts.stall_backend} is not a backend rank (with --ranks {nranks} the backends are {which})")


def run_reliefboards(comm, objects: BoardObjects, opts: ReliefboardOptions, cameras: list[Camera] | None,
                     sink=None, reference: bool = False, egl_device=None, tint_boards: bool = False):
    """Run M2 on every rank of ``comm`` (split into :data:`ROLES`): the visualization rank
    renders ``cameras`` (needed there only), the backends serve boards. ``sink(frame, image,
    stats)`` gets every frame on the visualization rank. Returns ``(records, extra)`` there and
    ``None`` elsewhere. The only collective after the split is the gather of the backends'
    counters once the last frame is done."""
    check_stall(opts, comm.Get_size())
    rc = split_roles(comm, ROLES)
    parent, viz, backends = rc.parent, rc.leader("visualization"), rc.ranks["backend"]
    if rc.role == "backend":
        counters = BackendRank(parent, viz, backends, objects, opts, egl_device).run()
        parent.gather(counters, root=viz)
        return None
    vis = VisualizationRank(parent, backends, objects, opts, egl_device, tint_boards)
    records = []
    try:
        for f, cam in enumerate(cameras):
            image, stats = vis.frame(cam, f)
            if reference and f % opts.reference_every == 0:
                ref_stats = FrameStats(frame=f, rank=0)
                ref = vis.render_reference(cam, ref_stats)
                stats.counters["ref_frame_ms"] = round(ref_stats.times_ms["draw"] + ref_stats.times_ms["readback"], 3)
                d = np.abs(image.color[..., :3].astype(np.int16) - ref.color[..., :3]).max(axis=2)
                stats.counters["ref_max_abs_diff"] = int(d.max(initial=0))
                stats.counters["ref_diff_fraction"] = float(np.count_nonzero(d) / d.size)
            if sink is not None:
                sink(f, image, stats)
            records.append(stats.to_json())
    finally:
        late = vis.close()
    gathered = parent.gather(None, root=viz)
    return records, {"late_boards": late, "backends": [g for g in gathered if g is not None], "renderer": vis.renderer}
