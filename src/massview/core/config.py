"""Render configuration: defaults → environment → frozen config → explicit arguments.

``RenderConfig.from_env(**explicit)`` starts from the defaults below, applies ``MASSVIEW_*``
environment variables (``MASSVIEW_CODEC``, ``MASSVIEW_RADIX_K``, ``MASSVIEW_EGL_DEVICE``), then
the explicit values (CLI flags); the result is frozen and validated, and is what travels to
every rank. Nothing below the app reads the environment itself.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, fields

from .errors import ConfigError

__all__ = ["RenderConfig", "parse_size", "parse_sun", "parse_grid"]


def parse_size(spec: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in spec.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {spec!r}: expected WIDTHxHEIGHT, e.g. 1280x1024") from None
    if not (1 <= w <= 32768 and 1 <= h <= 32768):
        raise ConfigError(f"--size {spec}: width and height must be between 1 and 32768")
    return w, h


def parse_grid(spec) -> tuple[int, int]:
    """``"ROWSxCOLS"`` (the CLI's form) or (rows, cols) → (rows, cols), both ≥ 1."""
    import numbers

    try:
        r, c = (int(v) for v in spec.lower().split("x")) if isinstance(spec, str) else spec
        ok = all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in (r, c))
    except (TypeError, ValueError):
        ok = False
    if not ok or r < 1 or c < 1:
        raise ConfigError(f"--grid {spec!r}: expected ROWSxCOLS with both at least 1, e.g. 2x3 or (2, 3)")
    return int(r), int(c)


CODEC_NAMES = ("auto", "none", "lz4", "blosc2")  # massview.parallel.codec.CODEC_CHOICES (checked by tests/test_codec_composite.py)
COMPOSITOR_NAMES = ("direct-send", "binary-swap", "radix-k")  # massview.parallel.composite.COMPOSITORS (kept here so that the CLI's parser need not import mpi4py)


@dataclass(frozen=True)
class RenderConfig:
    """Every option of a render, one field each: a CLI flag of ``massview render``/``view``
    (``cache_mb`` is ``--cache-mb``) and a keyword of :func:`massview.render`. Frozen and
    checked on construction; it is what travels to every rank.

    Decomposition and compositing:
        decomposition: ``sort-last[:MODE]`` or ``sort-first[:LAYOUT]`` (LAYOUT horizontal,
            vertical, grid, kd, balanced; MODE for a terrain kpatch, linear, quadtree; for a scene
            store visible, static). Default ``sort-last``.
        compositor: sort-last depth compositing: direct-send, binary-swap (default), radix-k.
        radix_k: k of radix-k (default 4).
        codec: sub-image codec between ranks: auto (default: none and raw rows on one node,
            blosc2 across nodes), none, lz4, blosc2.
        grid: (rows, cols) or ``"ROWSxCOLS"`` for ``sort-first:grid`` (default: chosen for the
            rank count).
        wall: ``"CxR"``: C×R display ranks each write their own tile.
        tile_targets: sort-first into tile-sized targets (equal to ~1e-4 of pixels).
        pipeline: ``"on"``: composite and deliver frame i on a thread while frame i+1 is drawn.

    Frames:
        width, height: image size in pixels (default 1280×1024; the API's ``size=``).
        frames: frames of the path (default 10).
        path: a built-in path name or a keyframe ``.json`` file (default ``orbit``).
        reference: also render each frame on one rank and report the difference.
        color_by_rank: tint each rank's contribution.
        egl_device: the EGL device index (default: the first; ``MASSVIEW_EGL_DEVICE``).

    Level of detail and memory (terrain stores and scene stores; ``builtin:objects`` is drawn
    whole from memory):
        tau: pixel tolerance of the LOD (default 1).
        cache_mb: RAM block cache per rank, MiB (default 256).
        gpu_mb: GL block pool per rank, MiB (default 256).
        loading: ``"complete"`` (default: wait for every block the view needs, final-quality
            frames) or ``"async"`` (never wait: draw coarser meanwhile; the viewer's).

    Terrain shading (terrain stores only):
        exaggeration: vertical exaggeration at view time (default 1; the LOD bound accounts for it).
        sun: (azimuth ° clockwise from north, altitude °), as gdaldem (default (315, 45)); also
            the CLI's ``"AZ,ALT"`` string.
        colormap: a matplotlib colormap name, ``hypsometric``, ``ortho``, ``none`` (grey) or
            ``auto`` (default: ``ortho`` where the store has an orthophoto).
        haze: aerial perspective strength (0 = off; default 1: 30 % towards the sky across the terrain).

    Systems:
        system: ``"auto"`` (by scene: T1 for a terrain, the scene renderer otherwise),
            ``"roettger"`` (T2), ``"dmmr"`` (M1) or ``"reliefboards"`` (M2).

    T2 (``system="roettger"``, terrain stores):
        layers: further stores drawn as stacked layers.
        compute_ranks: computation ranks; the other ranks visualize (default 1).
        paper_partition: the paper's overlapping (2^m+1)² portions instead of the exact partition.
        triangle_budget: at most N triangles per frame.
        roettger_C: minimum global resolution C (default: the store table's C_min).
        roettger_c: desired global resolution c (default: from ``tau``).
        fan_delta: send only the fans that changed since the previous frame (default True).

    M1 (``system="dmmr"``: rank 0 server, other ranks clients; scene stores and builtin:objects):
        visible_frames: frames a passed occlusion query keeps an object visible (default 4).
        query_threshold: samples (pixels) a box must pass to count as visible (default 0).
        occlusion: occlusion culling on the clients, ``"on"`` (default) or ``"off"``.
        query_hierarchy: queries through the group tree (``"on"``, default) or one per object box.
        occluder_lod: depth pre-pass at the rendered level (``"exact"``, default) or the coarsest.
        stage_pipeline: divide i / visibility i-1 / render i-2 concurrently (``"on"``, default).
        client_cache_mb: client RAM cache, MiB (default: the scene's object bytes / clients).
        record_ids: each client record lists the object ids it drew (``drawn_ids``).
        id_check: clients also render an ID buffer of their sub-frustum (``idbuffer_ids``,
            ``idbuffer_missed``).

    Testing aids (not user options; no CLI help):
        fault: ``"RANK:FRAME"``: raise on that rank at that frame.
        stage_delay: M1: ``"divide:MS,visibility:MS,render:MS"`` sleeps per stage.
    """

    decomposition: str = "sort-last"
    compositor: str = "binary-swap"
    radix_k: int = 4
    codec: str = "auto"
    width: int = 1280
    height: int = 1024
    frames: int = 10
    path: str = "orbit"
    grid: tuple[int, int] | None = None
    wall: str | None = None
    tile_targets: bool = False
    reference: bool = False
    color_by_rank: bool = False
    tau: float = 1.0
    cache_mb: int = 256
    gpu_mb: int = 256
    loading: str = "complete"
    exaggeration: float = 1.0
    sun: tuple[float, float] = (315.0, 45.0)
    colormap: str = "auto"
    haze: float = 1.0
    egl_device: int | None = None
    fault: str | None = None  # testing aid
    pipeline: str = "off"
    system: str = "auto"
    layers: tuple[str, ...] = ()
    compute_ranks: int = 1
    paper_partition: bool = False
    triangle_budget: int | None = None
    roettger_C: float | None = None
    roettger_c: float | None = None
    fan_delta: bool = True
    visible_frames: int = 4
    query_threshold: int = 0
    occlusion: str = "on"
    query_hierarchy: str = "on"
    occluder_lod: str = "exact"
    stage_pipeline: str = "on"
    client_cache_mb: int | None = None
    stage_delay: str | None = None  # testing aid
    record_ids: bool = False
    id_check: bool = False

    def __post_init__(self) -> None:
        self._check_types()
        if self.compositor not in COMPOSITOR_NAMES:
            raise ConfigError(f"--compositor must be one of {', '.join(COMPOSITOR_NAMES)}, got {self.compositor!r}")
        if self.frames < 1:
            raise ConfigError(f"--frames must be at least 1, got {self.frames}")
        if self.codec not in CODEC_NAMES:
            raise ConfigError(f"--codec (or MASSVIEW_CODEC) must be one of {', '.join(CODEC_NAMES)}, got {self.codec!r}")
        if self.radix_k < 2:
            raise ConfigError(f"--radix-k must be at least 2, got {self.radix_k}")
        if self.loading not in ("async", "complete"):
            raise ConfigError(f"--loading must be async or complete, got {self.loading!r}")
        if self.cache_mb < 1 or self.gpu_mb < 1:
            raise ConfigError("--cache-mb and --gpu-mb must be at least 1")
        if self.pipeline not in ("on", "off"):
            raise ConfigError(f"--pipeline must be on or off, got {self.pipeline!r}")
        if not self.tau > 0:
            raise ConfigError(f"--tau (pixel tolerance) must be positive, got {self.tau}")
        if self.system not in ("auto", "roettger", "dmmr", "reliefboards"):
            raise ConfigError(f"--system must be auto, roettger, dmmr or reliefboards, got {self.system!r}")
        if self.compute_ranks < 1:
            raise ConfigError(f"--compute-ranks must be at least 1, got {self.compute_ranks}")
        if self.triangle_budget is not None and self.triangle_budget < 1:
            raise ConfigError(f"--triangle-budget must be at least 1, got {self.triangle_budget}")
        if self.layers and self.system != "roettger":
            raise ConfigError("several stores (layers) need --system roettger")
        if self.reference and self.color_by_rank and self.system in ("auto", "dmmr"):
            raise ConfigError("--reference checks that the frame equals one rank's, and --color-by-rank tints each rank's part, so "
                              "the two differ by design (only --system roettger tints its reference alike): drop one of them")
        object.__setattr__(self, "layers", tuple(self.layers))
        if self.grid is not None:
            object.__setattr__(self, "grid", parse_grid(self.grid))
        self._check_shading()
        self._check_dmmr()

    def _check_types(self) -> None:
        """Each scalar option of the type its field declares (the Python API passes anything):
        a whole number for ``int`` fields (not a bool, not 2.5), a number for ``float`` ones, a
        string, a bool; ``None`` where the field allows it. Numbers are stored as plain Python
        ``int``/``float``. ``sun`` also takes the CLI's "AZIMUTH,ALTITUDE" string."""
        import numbers

        import numpy as np

        if isinstance(self.sun, str):
            object.__setattr__(self, "sun", parse_sun(self.sun))
        for f in fields(self):
            kind, v = str(f.type).replace(" ", ""), getattr(self, f.name)
            base, optional = (kind[:-5], True) if kind.endswith("|None") else (kind, False)
            if v is None and optional:
                continue
            flag = f"--{f.name.replace('_', '-')} ({f.name}=)"
            if base == "int":
                ok = isinstance(v, numbers.Integral) and not isinstance(v, bool)
                if not ok and isinstance(v, numbers.Real) and not isinstance(v, bool) and float(v).is_integer():
                    ok = True
                if not ok:
                    raise ConfigError(f"{flag} must be a whole number, got {v!r}")
                object.__setattr__(self, f.name, int(v))
            elif base == "float":
                if not isinstance(v, numbers.Real) or isinstance(v, bool):
                    raise ConfigError(f"{flag} must be a number, got {v!r}")
                object.__setattr__(self, f.name, float(v))
            elif base == "str" and not isinstance(v, str):
                raise ConfigError(f"{flag} must be a string, got {v!r}")
            elif base == "bool":
                if not isinstance(v, (bool, np.bool_)):
                    raise ConfigError(f"{flag} must be True or False, got {v!r}")
                object.__setattr__(self, f.name, bool(v))

    def _check_shading(self) -> None:
        if not (math.isfinite(self.exaggeration) and self.exaggeration > 0):
            raise ConfigError(f"--exaggeration must be a positive number, got {self.exaggeration}")
        sun = tuple(self.sun) if isinstance(self.sun, (tuple, list)) else ()
        if len(sun) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in sun) or not 0 <= sun[1] <= 90:
            raise ConfigError(f"--sun must be AZIMUTH,ALTITUDE in degrees with 0 ≤ altitude ≤ 90 (e.g. 315,45), got {self.sun!r}")
        object.__setattr__(self, "sun", (float(sun[0]) % 360.0, float(sun[1])))
        if not (isinstance(self.colormap, str) and self.colormap):
            raise ConfigError(f"--colormap must name a colour ramp, got {self.colormap!r}")
        if not (math.isfinite(self.haze) and self.haze >= 0):
            raise ConfigError(f"--haze must be 0 (off) or a positive strength, got {self.haze}")

    def _check_dmmr(self) -> None:
        if self.visible_frames < 1 or self.query_threshold < 0:
            raise ConfigError("--visible-frames must be at least 1 and --query-threshold at least 0")
        for name in ("occlusion", "stage_pipeline", "query_hierarchy"):
            if getattr(self, name) not in ("on", "off"):
                raise ConfigError(f"--{name.replace('_', '-')} must be on or off, got {getattr(self, name)!r}")
        if self.occluder_lod not in ("exact", "coarse"):
            raise ConfigError(f"--occluder-lod must be exact or coarse, got {self.occluder_lod!r}")
        if self.client_cache_mb is not None and self.client_cache_mb < 1:
            raise ConfigError("--client-cache-mb must be at least 1")
        for part in (self.stage_delay or "").split(","):
            name, _, ms = part.partition(":")
            if part and (name not in ("divide", "visibility", "render") or not ms.replace(".", "", 1).isdigit()):
                raise ConfigError(f"--stage-delay {self.stage_delay!r}: expected divide:MS,visibility:MS,render:MS")

    @classmethod
    def from_env(cls, env=None, **explicit) -> "RenderConfig":
        env = os.environ if env is None else env
        vals = {}
        if "MASSVIEW_CODEC" in env:
            vals["codec"] = env["MASSVIEW_CODEC"]
        if "MASSVIEW_RADIX_K" in env:
            vals["radix_k"] = int(env["MASSVIEW_RADIX_K"])
        if env.get("MASSVIEW_EGL_DEVICE"):
            vals["egl_device"] = int(env["MASSVIEW_EGL_DEVICE"])
        known = {f.name for f in fields(cls)}
        vals.update({k: v for k, v in explicit.items() if k in known and v is not None})
        return cls(**vals)

    def to_json(self) -> dict:
        return asdict(self)


def parse_sun(spec: str) -> tuple[float, float]:
    """``"AZIMUTH,ALTITUDE"`` (degrees) → (azimuth, altitude)."""
    try:
        az, alt = (float(v) for v in str(spec).split(","))
    except ValueError:
        raise ConfigError(f"--sun {spec!r}: expected AZIMUTH,ALTITUDE in degrees, e.g. 315,45") from None
    return az, alt
