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

__all__ = ["RenderConfig", "parse_size", "parse_sun"]


def parse_size(spec: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in spec.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {spec!r}: expected WIDTHxHEIGHT, e.g. 1280x1024") from None
    if not (1 <= w <= 32768 and 1 <= h <= 32768):
        raise ConfigError(f"--size {spec}: width and height must be between 1 and 32768")
    return w, h


CODEC_NAMES = ("auto", "none", "lz4", "blosc2")  # massview.parallel.codec.CODEC_CHOICES (checked by tests/test_codec_composite.py)
COMPOSITOR_NAMES = ("direct-send", "binary-swap", "radix-k")  # massview.parallel.composite.COMPOSITORS (kept here so that the CLI's parser need not import mpi4py)


@dataclass(frozen=True)
class RenderConfig:
    decomposition: str = "sort-last"
    compositor: str = "binary-swap"
    radix_k: int = 4
    codec: str = "auto"  # sub-image codec: auto (none + raw rows on one node, else blosc2), none, lz4, blosc2
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
    cache_mb: int = 256  # terrain: RAM block cache budget (MiB)
    gpu_mb: int = 256  # terrain: GL block pool budget (MiB)
    loading: str = "complete"  # terrain: "complete" (wait for every block the view needs: offline frames) or "async" (never wait: the viewer)
    exaggeration: float = 1.0  # terrain: vertical exaggeration at view time (the LOD bound accounts for it)
    sun: tuple[float, float] = (315.0, 45.0)  # terrain: sun azimuth (° clockwise from north), altitude (°), as gdaldem
    colormap: str = "auto"  # terrain: matplotlib colormap name, hypsometric, ortho, none (grey), auto (ortho if any)
    haze: float = 1.0  # terrain: aerial perspective strength (0 = off; 1 = 30 % towards the sky across the terrain)
    egl_device: int | None = None
    fault: str | None = None  # testing aid: "RANK:FRAME" raises on that rank at that frame
    pipeline: str = "off"  # "on": composite/deliver frame i on a thread while frame i+1 is drawn
    # T2 (--system roettger): computation ranks, partition, budget, Röttger's C and c, layers
    system: str = "auto"  # "auto" (by scene), "roettger" (T2), "dmmr" (M1) or "reliefboards" (M2)
    layers: tuple[str, ...] = ()  # further stores drawn as stacked layers (T2)
    compute_ranks: int = 1
    paper_partition: bool = False
    triangle_budget: int | None = None
    roettger_C: float | None = None  # None: the store table's C_min
    roettger_c: float | None = None  # None: from --tau (massview.lod.roettger.default_c)
    fan_delta: bool = True  # send only the fans that changed since the previous frame
    # M1 (--system dmmr): server + clients
    visible_frames: int = 4  # dmmr: frames a passed occlusion query keeps an object visible
    query_threshold: int = 0  # dmmr: samples (pixels) a box must pass to count as visible
    occlusion: str = "on"  # dmmr: occlusion culling on the clients, "on" or "off"
    query_hierarchy: str = "on"  # dmmr: occlusion queries through the group tree ("on") or one per object box ("off")
    occluder_lod: str = "exact"  # dmmr: depth pre-pass at the rendered level ("exact") or the coarsest ("coarse")
    stage_pipeline: str = "on"  # dmmr: divide i / visibility i-1 / render i-2 concurrently, or "off"
    client_cache_mb: int | None = None  # dmmr: client RAM cache (default: scene object bytes / clients)
    stage_delay: str | None = None  # testing aid: "divide:MS,visibility:MS,render:MS" sleeps per stage
    record_ids: bool = False  # dmmr: each client record lists the object ids it drew ("drawn_ids")
    id_check: bool = False  # dmmr: clients also render an ID buffer of their sub-frustum ("idbuffer_ids", "idbuffer_missed")

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
