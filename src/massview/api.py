"""The public Python API: what the CLI, the demo, the viewer and the benchmarks call.

A notebook session::

    import massview as mv

    scene = mv.open_scene("dem.zarr")                         # or "builtin:objects?n=400"
    cams = mv.path("flyover", scene, frames=4, size=(640, 480))
    res = mv.render(scene, cams, ranks=2, decomposition="sort-first:kd")
    res.images[0]                  # (480, 640, 3) uint8, top-left origin
    res.summary["imbalance"]       # the figures `massview render` writes to summary.json
    mv.show(res.images[0])         # displays inline in Jupyter (PNG)
    img = mv.render_frame(scene, mv.camera(scene, position=(0, 0, 3000), look_at=(5e4, -5e4, 0)))

**Options** of :func:`render` and :func:`render_frame` are the fields of
:class:`massview.core.config.RenderConfig` (``decomposition``, ``compositor``, ``tau``,
``loading``, ``color_by_rank``, ``reference``, ...), one keyword each; any field added to
``RenderConfig`` is a keyword here with no change to this module. Offline renders use
``RenderConfig``'s ``loading="complete"`` (every frame at the quality the budgets allow); the
viewer asks for ``"async"``.

**Ranks.** ``ranks=1`` renders in this process (the scene's GL context and caches stay open
between calls, so a notebook pays for them once). ``ranks=N > 1`` runs a real MPI job: the
scene name, the frozen config and the cameras are pickled into a temporary job folder, the job
is started as ``mpiexec -n N python -m massview __job DIR`` (the ``mpiexec`` beside this
Python), its ranks render collectively and write lossless PNG frames (+ ``depth/*.npy`` with
``depth=True``), ``stats.jsonl`` and ``summary.json``, and this process loads them back — so the
images are the job's pixels bit for bit. A rank's error is written to ``DIR/error.txt`` and
raised here as :class:`RankJobError` (:mod:`massview.app.render_job`). Inside an MPI job already (a script started by
``mpiexec``), :func:`render` is collective: every rank must call it, it uses all the ranks it
was given, and returns the result on rank 0 (``None`` elsewhere).
"""

from __future__ import annotations

import base64
import contextlib
import contextvars
import functools
import io
import json
import warnings
from dataclasses import MISSING, dataclass, fields
from pathlib import Path
from typing import Iterable

import numpy as np

from .core.camera import Camera, look_at_quaternion
from .core.config import RenderConfig, parse_size
from .core.errors import ConfigError, MassviewWarning, RankJobError
from .core.paths import BUILTIN_PATHS, load_path, scene_clip

__all__ = ["Scene", "RenderResult", "Frame", "RankJobError", "MassviewWarning", "open_scene", "camera", "path", "render",
           "render_frame", "show", "render_config", "prepare_terrain", "terrain_info", "verify_terrain", "upgrade_terrain",
           "prepare_scene", "scene_info", "verify_scene"]

# -- how messages name options: API keywords (tau=) for Python callers, flags (--tau) for the CLI --
_FLAG_NAMES = contextvars.ContextVar("massview_flag_names", default=False)


@contextlib.contextmanager
def flag_names():
    """Inside this block the API's errors and warnings name options as CLI flags (``--tau``)
    and warnings print as ``massview: warning:`` lines, as the CLI (which calls the API) shows
    them; outside, errors name keywords (``tau=``) and warnings are :class:`MassviewWarning`."""
    token = _FLAG_NAMES.set(True)
    try:
        yield
    finally:
        _FLAG_NAMES.reset(token)


def _keyword_errors(fn):
    """A public API function whose ConfigErrors name keywords (``size=``), not flags (``--size``)."""
    @functools.wraps(fn)
    def call(*args, **kw):
        try:
            return fn(*args, **kw)
        except ConfigError as e:
            if not _FLAG_NAMES.get():
                from .app.options import keyword_text

                e.args = (keyword_text(str(e)), *e.args[1:])  # (idempotent: a nested call's rewrite stays)
            raise

    return call


def _warn(messages) -> None:
    """Each message: a :class:`MassviewWarning` naming keywords, attributed to the caller's
    line, for Python callers; a ``massview: warning:`` line on stderr under :func:`flag_names`."""
    import inspect
    import os
    import sys

    from .app.options import keyword_text

    here, f, level = os.path.dirname(os.path.abspath(__file__)), inspect.currentframe(), 1
    while f is not None and os.path.abspath(f.f_code.co_filename).startswith(here + os.sep):
        f, level = f.f_back, level + 1
    for m in messages:
        if _FLAG_NAMES.get():
            print(f"massview: warning: {m}", file=sys.stderr, flush=True)
        else:
            warnings.warn(keyword_text(m), MassviewWarning, stacklevel=level)


class Scene:
    """An open scene: a terrain store, a scene store (polygon models, ``massview prepare scene``
    or ``massview generate scene``) or ``builtin:objects[?n=..&seed=..]`` (``kind`` is
    ``"terrain"``, ``"scene"`` or ``"objects"``).

    ``bounds`` is the world-space box ``(lo, hi)`` (float64 (3,), metres, +z up) the built-in
    paths and the clip planes are fitted to. The in-process system (GL context, block caches)
    is opened on first use and kept for later ``ranks=1`` renders; :meth:`close` frees it.
    """

    def __init__(self, spec: str | Path):
        from .systems import scene_kind

        self.spec = str(spec)
        self.kind = scene_kind(self.spec)  # raises SceneNotFoundError / StoreError naming the problem
        self._system, self._key, self._bounds = None, None, None

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self._bounds is None:
            b = self._system.bounds if self._system is not None and self.kind != "terrain" else scene_bounds(self.spec, self.kind)
            self._bounds = tuple(np.asarray(v, np.float64) for v in b)
        return self._bounds

    @property
    def obstacles(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The objects' boxes ``(box_lo, box_hi)`` that the ``walkthrough`` path walks round, as
        the system reports them (None for a terrain), from metadata alone."""
        if self._system is not None:
            return getattr(self._system, "obstacles", None)
        return scene_obstacles(self.spec, self.kind)

    def ground(self, exaggeration: float = 1.0):
        """The surface the ``walkthrough`` path walks on: a terrain's (``xy (n, 2) -> z (n,)``,
        world units, at ``exaggeration``), from the store alone; None for other scenes."""
        if self.kind != "terrain":
            return None
        from .data.terrain import TerrainStore
        from .lod.walk import kpatch_ground

        return kpatch_ground(TerrainStore(self.spec), exaggeration)

    def system(self, cfg: RenderConfig):
        """The in-process rendering system for ``cfg`` (reopened when budgets or loading change)."""
        from .systems import open_system

        key = (cfg.cache_mb, cfg.gpu_mb, cfg.loading, cfg.egl_device)
        if self._system is None or key != self._key:
            self.close()
            self._system, self._key = open_system(self.spec, cfg), key
        return self._system

    def close(self) -> None:
        if self._system is not None and hasattr(self._system, "close"):
            self._system.close()
        self._system = None

    def __enter__(self) -> "Scene":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        lo, hi = self.bounds
        return f"Scene({self.spec!r}, {self.kind}, bounds {np.round(lo, 1).tolist()} .. {np.round(hi, 1).tolist()})"


def scene_obstacles(spec: str, kind: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The object boxes the system for ``spec`` gives the ``walkthrough`` path (its
    ``obstacles``), from metadata alone: a scene store's skeleton boxes, ``builtin:objects``'
    generated objects; None for a terrain."""
    if kind == "scene":
        from .data.scene import SceneStore

        return SceneStore(spec).object_boxes
    if kind == "terrain":
        return None
    from .systems.objects import ObjectsSystem

    return ObjectsSystem(spec).obstacles


def scene_bounds(spec: str, kind: str, system: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """The world box ``(lo, hi)`` (float64 (3,)) the system for ``spec`` reports, from metadata
    alone: no GL context, no caches, no K-patch hierarchy (the parent of a ``ranks=N`` job calls
    this to fit paths and clip planes; opening the system cost 560 MiB at 32769²).

    * terrain, T1: the whole-domain height range ``lod/zmin/0``, ``lod/zmax/0`` through
      :func:`massview.lod.kpatch.world_box`, the hierarchy's own formula;
    * terrain, ``system="roettger"`` (T2): its layers' attributes (``RoettgerSystem.bounds``
      before setup reads nothing else);
    * scene store: the skeleton's boxes; ``builtin:objects``: the generated objects' boxes
      (the scene is its own metadata; GL is opened only to draw)."""
    if kind == "terrain" and system == "roettger":
        from .systems.roettger import RoettgerSystem

        return RoettgerSystem([spec], RenderConfig(system="roettger")).bounds
    if kind == "terrain":
        from .data.terrain import TerrainStore
        from .lod.kpatch import world_box

        st = TerrainStore(spec)
        return world_box(st.layout, *st.height_ranges(0), st.spacing, st.vertical_scale)
    if kind == "scene":
        from .data.scene import SceneStore

        return SceneStore(spec).bounds
    from .systems.objects import ObjectsSystem

    return ObjectsSystem(spec).bounds


def open_scene(spec: str | Path | Scene) -> Scene:
    """Open a terrain store folder, a scene store folder or ``builtin:objects[?n=COUNT&seed=S]``
    (a :class:`Scene` is returned as is). Nothing heavy is opened until the first render."""
    if not isinstance(spec, (str, Path, Scene)):
        raise ConfigError(f"open_scene(): give a store folder (str or Path), builtin:objects or a Scene, got {type(spec).__name__} {spec!r}")
    return spec if isinstance(spec, Scene) else Scene(spec)


def _bounds(scene) -> tuple[np.ndarray, np.ndarray]:
    """The world box of a Scene, or of a spec (opened and closed again)."""
    if isinstance(scene, Scene):
        return scene.bounds
    with Scene(scene) as s:
        return s.bounds


def _fitted_path(name: str, scene, exaggeration: float = 1.0):
    """The path ``name`` fitted to a Scene or a spec (opened and closed again): its box and, for
    ``walkthrough``, the way round its objects or the terrain it walks on (what the CLI's render
    gives it)."""
    if not isinstance(scene, Scene):
        with Scene(scene) as s:
            return _fitted_path(name, s, exaggeration)
    from .core.paths import exaggerated_box
    from .lod.walk import fit_path

    walk = name == "walkthrough"
    box = exaggerated_box(*scene.bounds, exaggeration) if scene.kind == "terrain" else scene.bounds
    return fit_path(name, *box, scene.obstacles if walk or name == "flyover" else None,
                    scene.ground(exaggeration) if walk else None)


def _size(size) -> tuple[int, int]:
    if isinstance(size, str):
        return parse_size(size)
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ConfigError(f"size {size!r}: expected (width, height) or 'WIDTHxHEIGHT'") from None
    return parse_size(f"{w}x{h}")


@_keyword_errors
def camera(scene: Scene | str | None = None, *, position, look_at=None, orientation=None, fovy: float = 45.0,
           size=(1280, 1024), near: float | None = None, far: float | None = None) -> Camera:
    """A camera at ``position`` (world metres) looking at ``look_at`` (or with a unit quaternion
    ``orientation`` (w, x, y, z)). ``near``/``far`` default to clip planes fitted to the scene."""
    pos = _vector(position, 3, "position", "(x, y, z)")
    if orientation is None:
        if look_at is None:
            raise ConfigError("camera(): give look_at=(x, y, z) or orientation=(w, x, y, z)")
        target = _vector(look_at, 3, "look_at", "(x, y, z)")
        if np.allclose(target, pos):
            raise ConfigError("camera(): look_at is the position itself; look at another point")
        orientation = look_at_quaternion(pos, target)
    else:
        orientation = _vector(orientation, 4, "orientation", "(w, x, y, z)")
    if near is None or far is None:
        if scene is None:
            raise ConfigError("camera(): give the scene (to fit the clip planes) or near= and far=")
        fn, ff = scene_clip(*_bounds(scene), positions=pos[None])
        near, far = near if near is not None else fn, far if far is not None else ff
    w, h = _size(size)
    return Camera(tuple(pos), tuple(orientation), fovy=fovy, near=near, far=far, width=w, height=h)


def _vector(v, n: int, name: str, form: str) -> np.ndarray:
    """``v`` as n finite float64 numbers; ConfigError naming ``name`` otherwise."""
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"camera(): {name} must be {n} finite numbers {form}, got {v!r}")
    return a


def _count(v, name: str) -> int:
    """A whole number ≥ 1 (``frames``, ``ranks``): ConfigError naming ``name`` otherwise."""
    import numbers

    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not float(v).is_integer() or v < 1:
        raise ConfigError(f"{name}= must be a whole number ≥ 1, got {v!r}")
    return int(v)


@_keyword_errors
def path(name_or_file: str | Path, scene: Scene | str, frames: int = 10, size=(1280, 1024),
         exaggeration: float = 1.0) -> list[Camera]:
    """``frames`` cameras along a built-in path (``turn``, ``zoom``, ``forward``, ``orbit``,
    ``flyover``, ``walkthrough``, fitted to the scene; ``walkthrough`` walks round its objects, or
    at eye height on a terrain)
    or a keyframe ``.json`` file (clip planes fitted to the
    scene unless the file gives ``near``/``far``). ``exaggeration``: a terrain's, as you will
    render it (``render(..., exaggeration=)``): the path flies over, and walks on, the relief as
    drawn at it."""
    w, h = _size(size)
    e = render_config(exaggeration=exaggeration).exaggeration  # (checked as render's own option)
    return _fitted_path(str(name_or_file), scene, e).cameras(_count(frames, "frames"), w, h)


@_keyword_errors
def render_config(config: RenderConfig | None = None, **options) -> RenderConfig:
    """A :class:`RenderConfig` from ``config`` (default: environment + offline defaults) and
    keyword overrides; an unknown keyword is a :class:`ConfigError` listing the known ones.
    ``config`` may also be a dict of options (the keywords win over it)."""
    if isinstance(config, dict):
        options, config = {**config, **options}, None
    elif config is not None and not isinstance(config, RenderConfig):
        raise ConfigError(f"config= takes a RenderConfig (massview.render_config(...)) or a dict of options, got {type(config).__name__}")
    known = {f.name for f in fields(RenderConfig)}
    bad = sorted(set(options) - known)
    if bad:
        raise ConfigError(f"unknown render option(s) {', '.join(bad)}; options are the RenderConfig fields: {', '.join(sorted(known))}")
    if config is None:
        return RenderConfig.from_env(**options)
    return RenderConfig(**{**config.to_json(), **{k: v for k, v in options.items() if v is not None}})


@dataclass
class RenderResult:
    """What :func:`render` returns.

    ``images``: one (H, W, 3) uint8 array per frame (top-left origin), None with ``images=False``;
    ``depths``: (H, W) float32 window depth in [0, 1] per frame (1 = background) with ``depth=True``;
    ``summary``: the figures of ``summary.json`` (fps, triangles_per_rank, imbalance, bytes_per_frame, ...);
    ``stats``: the per-frame per-rank records of ``stats.jsonl``; ``out``: the output folder, if any.
    """

    images: list[np.ndarray] | None
    depths: list[np.ndarray] | None
    summary: dict
    stats: list[dict]
    out: Path | None = None

    def frame_stats(self, frame: int) -> list[dict]:
        """The records of one frame, one per rank."""
        return [r for r in self.stats if r["frame"] == frame]

    def __len__(self) -> int:
        return int(self.summary.get("frames", len(self.images or [])))

    def __repr__(self) -> str:  # (the dataclass's own would print every pixel)
        size = f"{self.images[0].shape[1]}x{self.images[0].shape[0]}" if self.images else "no images"
        fps = self.summary.get("fps")
        return (f"RenderResult({len(self)} frames, {size}, {_ranks(self.summary)} ranks"
                + (f", {fps:.1f} fps" if isinstance(fps, (int, float)) else "") + (f", out={str(self.out)!r}" if self.out else "") + ")")

    def _repr_png_(self) -> bytes | None:
        return show(self.images[0]).png() if self.images else None


def _ranks(summary: dict) -> int:
    """The ranks a run used: M2's summary counts its backends (plus the visualization rank)."""
    if summary.get("system") == "reliefboards" and isinstance(summary.get("backends"), int):
        return summary["backends"] + 1
    return summary.get("ranks", 1)


def _cameras(scene: Scene, what, cfg: RenderConfig) -> tuple[list[Camera], str]:
    if isinstance(what, Camera):
        return [what], "camera"
    if isinstance(what, (str, Path)):
        p = _fitted_path(str(what), scene, cfg.exaggeration)
        times = getattr(p, "times", None)  # (a keyframe file's)
        if times is not None and len(times) > 1 and float(np.ptp(times)) == 0.0 and cfg.frames > 1:
            _warn_rank0([f"{what}: all {len(times)} keyframes have time {float(times[0]):g}: every frame shows keyframe 0 "
                         "(a still); give them increasing times"])
        elif times is not None and len(times) == 1 and cfg.frames > 1:
            _warn_rank0([f"{what}: one keyframe, so all {cfg.frames} frames show it (a still); add keyframes with later "
                         "times to move the camera"])
        return p.cameras(cfg.frames, cfg.width, cfg.height), str(what)
    try:
        cams = list(what)
    except TypeError:
        cams = []
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise ConfigError("render(): give a path name, a keyframe .json file, a Camera or a list of Cameras")
    if len({(c.width, c.height) for c in cams}) != 1:
        raise ConfigError("render(): every camera of one render must have the same image size")
    return cams, "cameras"


@_keyword_errors
def render(scene: Scene | str | Path, what: str | Path | Camera | Iterable[Camera] | None = None, *, ranks: int | None = None,
           out: str | Path | None = None, depth: bool = False, images: bool = True, progress: bool = False,
           frames: int | None = None, size=None, config: RenderConfig | None = None, reliefboards=None,
           **options) -> RenderResult | None:
    """Render a path or cameras on ``ranks`` local ranks (see the module docstring).

    ``what``: a path name or keyframe file (with ``frames`` and ``size``; default: the ``path``
    option, ``"orbit"``), a :class:`Camera`, or a list of cameras. ``out``: also write ``frames/``, ``stats.jsonl`` and ``summary.json`` there.
    ``options``: :class:`RenderConfig` fields. Returns a :class:`RenderResult` (``None`` on ranks
    other than 0 when called collectively inside an MPI job). ``system="reliefboards"`` (M2)
    runs its own role loop (:mod:`massview.systems.reliefboards_job`); ``reliefboards``: its
    ``ReliefboardOptions`` or a dict of their fields (``t_nz``, ``epsilon_deg``, ...).

    An option the scene or system does not use (``exaggeration=`` on a polygon scene,
    ``compute_ranks=`` without ``system="roettger"``, ...) gives a :class:`MassviewWarning`;
    ``frames=``/``size=`` that disagree with given cameras, and ``decomposition="sort-last"``
    with ``system="dmmr"`` (which divides the screen), are a :class:`ConfigError`.
    """
    cfg = render_config(config, **options)
    given = _given(config, options)
    what = _given_cameras(what, frames, size)
    if cfg.system == "reliefboards":  # M2: one visualization rank and backends (issue 19)
        from .systems import scene_kind
        from .systems.reliefboards_job import render_reliefboards

        if what is None or isinstance(what, (str, Path)):
            w, h = _size(size) if size is not None else (cfg.width, cfg.height)
            cfg = RenderConfig(**{**cfg.to_json(), "width": w, "height": h, "frames": cfg.frames if frames is None else _count(frames, "frames")})
        spec = scene.spec if isinstance(scene, Scene) else str(scene)
        check_render_out(out, spec)
        kind = scene_kind(spec)
        if kind != "terrain":  # (a terrain store is refused by render_reliefboards itself)
            warn_options(spec, kind, cfg, given)
        return render_reliefboards(spec, what, cfg, ranks, out, images, depth, reliefboards, result=RenderResult)
    owned = not isinstance(scene, Scene)
    scene = open_scene(scene)
    try:
        return _render(scene, what, ranks, out, depth, images, progress, frames, size, cfg, given)
    finally:
        if owned:
            scene.close()


def _given(config, options: dict) -> set[str]:
    """The options a caller gave (judged by :func:`massview.app.options.option_warnings`):
    keywords passed (not None), a dict config's keys, a RenderConfig's fields that differ from
    the defaults."""
    given = {k for k, v in options.items() if v is not None}
    if isinstance(config, dict):
        given |= {k for k, v in config.items() if v is not None}
    elif isinstance(config, RenderConfig):
        given |= {f.name for f in fields(RenderConfig) if f.default is not MISSING and getattr(config, f.name) != f.default}
    return given


def _blind(cams: list[Camera], scene: Scene, cfg: RenderConfig) -> str | None:
    """A warning when no camera's view volume reaches the scene's box (as drawn at
    ``cfg.exaggeration``): keyframes written in the wrong coordinates (a terrain's CRS instead
    of its world metres), every frame all sky. Conservative: a camera counts as seeing the box
    unless one of its planes has all 8 corners outside."""
    from .core.paths import exaggerated_box

    lo, hi = exaggerated_box(*scene.bounds, cfg.exaggeration) if scene.kind == "terrain" else scene.bounds
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    if any(((c.frustum_planes() @ corners.T) >= 0).any(axis=1).all() for c in cams):
        return None
    where = ("world metres: x east = column × dx from the west edge, y north = −row × dy from the north edge, "
             "not the store's CRS coordinates" if scene.kind == "terrain" else "world units")
    box = ", ".join(f"{a} {lo[k]:.6g}..{hi[k]:.6g}" for k, a in enumerate("xyz"))
    who = f"none of the {len(cams)} cameras looks" if len(cams) > 1 else "the camera does not look"
    return f"{who} at the scene ({box}; {where}): every frame will be sky only"


def _buried(cams: list[Camera], scene: Scene, cfg: RenderConfig) -> str | None:
    """A warning for the first camera inside a terrain's box below its lowest point (under the
    ground: the frame shows the terrain's underside)."""
    if scene.kind != "terrain":
        return None
    lo, hi = scene.bounds
    for n, c in enumerate(cams):
        x, y, z = c.position
        if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and z < lo[2]:
            return (f"camera {n} is {lo[2] - z:.6g} m below the terrain's lowest point (z {lo[2]:.6g}) inside its extent: "
                    "its frame shows the terrain from below")
    return None


def _warn_rank0(lines) -> None:
    """:func:`_warn` on rank 0 only inside an MPI job; nothing for no lines."""
    from .parallel.runtime import in_mpi_job, world

    if lines and (not in_mpi_job() or world().Get_rank() == 0):
        _warn(lines)


def _given_cameras(what, frames, size):
    """``what`` (a list where it was an iterable of cameras); ``frames=`` and ``size=`` with
    cameras must agree with them (they apply to a path name: were silently ignored)."""
    if what is None or isinstance(what, (str, Path)):
        return what
    try:
        cams = [what] if isinstance(what, Camera) else list(what)
    except TypeError:
        return what  # (_cameras names what to give)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        return what if isinstance(what, Camera) else cams
    if frames is not None and _count(frames, "frames") != len(cams):
        raise ConfigError(f"frames={frames!r} with {len(cams)} camera{'s' if len(cams) > 1 else ''}: cameras render one frame each; "
                          "frames= (and size=) apply to a path name: leave frames= out")
    w, h = cams[0].width, cams[0].height
    if size is not None and _size(size) != (w, h):
        raise ConfigError(f"size={size!r} with cameras of {w}x{h}: cameras carry their own image size (camera(..., size=), "
                          "path(..., size=)); size= applies to a path name: leave it out")
    return what if isinstance(what, Camera) else cams


def warn_options(spec: str, kind: str, cfg: RenderConfig, given) -> None:
    """Warnings for the ``given`` options that have no effect on ``spec`` with ``cfg``
    (:func:`massview.app.options.option_warnings`), through :func:`_warn` (rank 0 only inside an
    MPI job): the API's and the CLI's one way to say so."""
    from .app.options import option_warnings

    _warn_rank0(option_warnings(spec, kind, cfg, given))


def _not_inside_the_store(out: Path, spec: str) -> None:
    """--out must not be the input store or a folder inside it, nor any other massview store
    or a folder inside one (frames, stats and a summary would be written among its arrays)."""
    o = Path(out).resolve()
    store = Path(spec)
    if store.is_dir():
        st = store.resolve()
        if o == st or st in o.parents:
            raise ConfigError(f"--out {out}: is {'the input store' if o == st else 'inside the input store'} {spec}; "
                              "give a folder outside it for the frames, stats and summary")
    from .data.scene.writer import enclosing_store

    d = o if (o / "zarr.json").is_file() else enclosing_store(o)
    if d is not None:
        raise ConfigError(f"--out {out}: {'is' if d == o else 'is inside'} the store {d}; "
                          "give a folder outside it for the frames, stats and summary")


def check_render_out(out, spec: str) -> Path | None:
    """``out`` checked before any rank starts (outside every store, a writable folder)."""
    from .app.outputs import check_output_dir

    if out is None:
        return None
    _not_inside_the_store(Path(out), spec)
    return check_output_dir(Path(out), "--out")


def _render(scene: Scene, what, ranks, out, depth, images, progress, frames, size, cfg: RenderConfig, given=()) -> RenderResult | None:
    from .parallel.runtime import in_mpi_job, world

    nranks = world().Get_size() if in_mpi_job() else (1 if ranks is None else _count(ranks, "ranks"))
    what = cfg.path if what is None else what
    if isinstance(what, (str, Path)):  # size and frame count first: check everything before any work
        w, h = _size(size) if size is not None else (cfg.width, cfg.height)
        cfg = RenderConfig(**{**cfg.to_json(), "width": w, "height": h, "frames": cfg.frames if frames is None else _count(frames, "frames"),
                              "path": str(what)})
        load_path(str(what), [0, 0, 0], [1, 1, 1])  # a bad name or file is reported now
    out = Path(out) if out is not None else None
    validate(scene.spec, cfg, nranks)
    warn_options(scene.spec, scene.kind, cfg, given)
    check_render_out(out, scene.spec)
    if nranks == 1 or in_mpi_job():
        scene.system(cfg)  # opened with this config's budgets (the bounds come from it)
    cams, label = _cameras(scene, what, cfg)
    if not (isinstance(what, str) and what in BUILTIN_PATHS):
        _warn_rank0([m for m in (_blind(cams, scene, cfg), _buried(cams, scene, cfg)) if m])
    cfg = RenderConfig(**{**cfg.to_json(), "width": cams[0].width, "height": cams[0].height, "frames": len(cams)})
    validate(scene.spec, cfg, nranks)
    if in_mpi_job() or nranks == 1:
        return _render_here(scene, cfg, cams, label, out, depth, images, progress)
    return _render_job(scene, cfg, cams, label, out, depth, images, progress, nranks)


@_keyword_errors
def render_frame(scene: Scene | str | Path, what: Camera | str | Path | None = None, *, depth: bool = False, **kw):
    """One frame: (H, W, 3) uint8, or ``(rgb, depth)`` with ``depth=True``. ``what`` is a camera
    or a path (its first camera); other keywords as :func:`render`. A list of several cameras
    is refused (:func:`render` renders them all)."""
    if what is None or isinstance(what, (str, Path)):
        kw.setdefault("frames", 1)
    elif isinstance(what, (list, tuple)):
        if len(what) != 1:
            raise ConfigError(f"render_frame renders one camera, and got a list of {len(what)}: pass one of them "
                              "(e.g. cams[0]), or use render(scene, cams) for every one")
        what = what[0]
    res = render(scene, what, depth=depth, **kw)
    if res is None:
        return None
    return (res.images[0], res.depths[0]) if depth else res.images[0]


def validate(spec: str, cfg: RenderConfig, nranks: int) -> None:
    """Cheap checks before any rank starts, so a bad option is reported once."""
    from .parallel.decompose import parse_decomposition, parse_wall, sort_first_tiles
    from .systems import scene_kind

    kind = scene_kind(spec)
    modes = {"terrain": ("kpatch", "linear", "quadtree"), "scene": ("visible", "static")}.get(kind, ())
    if cfg.system == "roettger" and kind != "terrain":  # (walk8 L5: "not a massview terrain store", exit 1, or a prepare hint for builtin:)
        what = "builtin:objects is a polygon scene" if kind == "objects" else f"{spec} is a scene store"
        raise ConfigError(f"--system roettger (T2) draws terrain stores, and {what}: leave --system out (T1 draws scenes too) "
                          "or use --system dmmr (M1) or --system reliefboards (M2)")
    if cfg.system == "dmmr" and kind == "terrain":
        raise ConfigError(f"--system dmmr draws polygon scenes (a scene store or builtin:objects), and {spec} is a terrain store: "
                          "leave --system out (T1) or use --system roettger (T2)")
    if kind == "terrain" and cfg.colormap != "auto":
        from .render.colormaps import ramp

        ramp(cfg.colormap)  # a name matplotlib does not know: ConfigError now, not after the ranks started
    if kind == "terrain" and cfg.system != "roettger":  # a --gpu-mb too small for one block: now, not after the
        from .data.rebuild import store_attrs         # earlier run's outputs were cleared (walk7 M1)
        from .render.terrain_pool import check_pool_budget

        attrs = store_attrs(spec) or {}
        if isinstance(attrs.get("M"), int):
            check_pool_budget(int(cfg.gpu_mb) << 20, attrs["M"], attrs.get("color") == "orthophoto")
    if cfg.system == "roettger":  # T2: roles, wall per visualization rank, the stores' tables
        from .systems.roettger import validate as validate_roettger

        return validate_roettger(spec, cfg, nranks)
    if cfg.system == "dmmr" and (cfg.wall or cfg.tile_targets):  # (walk8 L1: refused only inside the ranks, under MPI_Abort)
        from .systems.dmmr import NO_WALL

        raise ConfigError(NO_WALL)
    parse_decomposition(cfg.decomposition, modes)
    if cfg.decomposition == "sort-first:grid":
        sort_first_tiles("grid", nranks, cfg.width, cfg.height, cfg.grid)
    if cfg.wall:
        parse_wall(cfg.wall, nranks, cfg.width, cfg.height)


def _render_here(scene, cfg, cams, label, out, depth, images, progress) -> RenderResult | None:
    from .app.render_cmd import run_render
    from .parallel.runtime import guarded, in_mpi_job, self_comm, world

    if in_mpi_job():  # collective: every rank opens its own system; errors end every rank
        comm = world()
        job = guarded(comm, run_render, comm, scene.spec, cfg, out, not progress, cams if comm.Get_rank() == 0 else None,
                      images, depth, label)
    else:
        job = run_render(self_comm(), scene.system(cfg), cfg, out, not progress, cams, images, depth, label)
    if job is None:
        return None
    imgs = deps = None
    if images:
        from .app.render_job import assemble_tiles

        frames = [assemble_tiles(job.tiles.get(f, []), cfg.width, cfg.height) for f in range(len(cams))]
        imgs = [f[0] for f in frames]
        deps = [f[1] for f in frames] if depth else None
    return RenderResult(imgs, deps, job.summary, job.records, out)


# -- ranks > 1: a real MPI job (app/render_job.py) -------------------------------------------
def _render_job(scene, cfg, cams, label, out, depth, images, progress, nranks) -> RenderResult:
    from .app.render_job import load_frames, mpi_job
    from .core.stats import read_stats

    with mpi_job(scene.spec, cfg, cams, label, out, depth, not progress, nranks) as folder:
        summary = json.loads((folder / "summary.json").read_text())
        records = read_stats(folder / "stats.jsonl")
        imgs, deps = load_frames(folder, cfg, len(cams), depth, summary["ranks"]) if images else (None, None)
    return RenderResult(imgs, deps, summary, records, out)


# -- display in notebooks --------------------------------------------------------------------
class Frame:
    """An image that Jupyter displays inline (``_repr_png_``); ``array`` is (H, W, 3) uint8."""

    def __init__(self, array: np.ndarray):
        a = np.asarray(array)
        if a.ndim != 3 or a.shape[2] not in (3, 4) or a.dtype != np.uint8:
            raise ConfigError(f"show(): expected an (H, W, 3|4) uint8 image, got {a.shape} {a.dtype}")
        self.array = np.ascontiguousarray(a[..., :3])

    def png(self) -> bytes:
        from PIL import Image as PILImage

        buf = io.BytesIO()
        PILImage.fromarray(self.array).save(buf, format="PNG")
        return buf.getvalue()

    def _repr_png_(self) -> bytes:
        return self.png()

    def _repr_html_(self) -> str:
        h, w = self.array.shape[:2]
        return f'<img width="{w}" height="{h}" src="data:image/png;base64,{base64.b64encode(self.png()).decode()}"/>'

    def save(self, path: str | Path) -> Path:
        Path(path).write_bytes(self.png())
        return Path(path)

    def __repr__(self) -> str:
        return f"Frame({self.array.shape[1]}x{self.array.shape[0]})"


def show(img, frame: int = 0) -> Frame:
    """A displayable :class:`Frame` of an (H, W, 3|4) uint8 array, a :class:`RenderResult`
    (its frame ``frame``) or a PNG file. In Jupyter, ``mv.show(img)`` as a cell's last line
    displays it; elsewhere ``.save(path)`` writes the PNG. No IPython import is needed."""
    if isinstance(img, RenderResult):
        if not img.images:
            raise ConfigError("show(): this result holds no images (rendered with images=False)")
        if not (isinstance(frame, int) and -len(img.images) <= frame < len(img.images)):
            raise ConfigError(f"show(): frame {frame!r} of a {len(img.images)}-frame result (frames 0..{len(img.images) - 1})")
        img = img.images[frame]
    elif isinstance(img, (str, Path)):
        from PIL import Image as PILImage

        with PILImage.open(img) as im:
            img = np.asarray(im.convert("RGB"))
    elif hasattr(img, "color") and hasattr(img, "viewport"):  # a massview.core.image.Image
        img = img.color
    return Frame(img)



# -- terrain stores: what `massview prepare terrain`, `info` and `verify` do --------------------

def prepare_terrain(input: str | Path, out: str | Path, *, color: str | Path | None = None, nodata: float | None = None,
                    spacing=None, crs: str | None = None, block: int = 257, vertical_scale: float = 1.0,
                    overwrite: bool = False, workers: int = 0, array: str | None = None, shape: tuple[int, int] | None = None,
                    dtype: str | None = None, progress: bool = False):
    """Prepare the terrain store ``out`` from the DEM file ``input`` (GeoTIFF/COG, ``.npy``,
    ``.npz`` with ``array=``, SRTM ``.hgt``, raw binary with ``shape=(rows, cols)`` and
    ``dtype=``), as ``massview prepare terrain`` does: ``color`` an orthophoto to drape,
    ``nodata`` the void value (default: the file's own), ``spacing`` ``DX`` or ``(DX, DY)`` metres
    and ``crs`` for an input without a georeference, ``block`` 129/257/513, ``vertical_scale``
    heights to metres, ``overwrite`` to replace a complete store (an interrupted one is
    resumed), ``workers`` threads (0: every core), ``progress`` bars on stderr. Returns the
    :class:`massview.data.terrain.ingest.PrepareResult` (``path``, ``layout``, ``seconds``,
    ``filled``, ``warnings``, …); its warnings also come as :class:`MassviewWarning`. Errors
    name the file or the option, as the CLI's do."""
    from .app.terrain_cmds import prepare_file

    res = prepare_file(input, out, option="out=", quiet=not progress, color=color, nodata=nodata, array=array,
                       shape=None if shape is None else tuple(int(v) for v in shape), dtype=dtype, spacing=spacing, crs=crs,
                       block=block, vertical_scale=vertical_scale, overwrite=overwrite, workers=workers)
    _warn(res.warnings)
    return res


def terrain_info(store: str | Path) -> dict:
    """What ``massview info STORE --json`` prints: samples, layout, spacing, CRS, nodata, colour,
    disk use, compression and the world box keyframe files use (None for an incomplete store)."""
    from .app.terrain_cmds import store_info

    return store_info(Path(store))


def verify_terrain(store: str | Path, progress: bool = False) -> list[str]:
    """The problems ``massview verify STORE`` finds (every array's shape, every block decodes,
    metadata and the Röttger table match the data); an empty list for a sound store."""
    from .app.terrain_cmds import progress_bar
    from .data.terrain.verify import verify_store

    with progress_bar(not progress) as prog:
        return verify_store(Path(store), prog)


def upgrade_terrain(store: str | Path, progress: bool = False) -> str | None:
    """What ``massview upgrade STORE`` does: bring a store of an older format to the current one
    in place, or on a current store write again any halo row the heights do not give and remove
    a leftover ``shade/0``; returns what was done (a sentence), None when nothing was to do."""
    from .app.terrain_cmds import progress_bar
    from .data.terrain.upgrade import upgrade_store

    with progress_bar(not progress) as prog:
        return upgrade_store(Path(store), prog)


def prepare_scene(inputs, out: str | Path, *, object_triangles: int = 16384, object_size: float | None = None,
                  instance: bool = False, simplifier: str = "fast-simplification", levels: int = 8, stream_mb: float = 256,
                  crease_angle: float | None = None, up: str = "auto", overwrite: bool = False, progress: bool = False) -> dict:
    """Prepare the scene store ``out`` from mesh files (PLY, OBJ, STL, OFF, glTF/GLB; one path or
    a list), as ``massview prepare scene`` does, with its options as keywords (``object_triangles``,
    ``object_size``, ``instance``, ``simplifier``, ``levels``, ``stream_mb``, ``crease_angle``
    (degrees; default the CLI's), ``up`` "auto"/"y"/"z", ``overwrite``; ``progress`` bars on
    stderr). Returns the store's figures (``objects``, ``geometries``, ``triangles``, ``seconds``,
    ``warnings``, …); the warnings also come as :class:`MassviewWarning`. Errors name the file or
    the option, as the CLI's do."""
    from .app.scene_cmds import CREASE_ANGLE, prepare_files

    paths = [inputs] if isinstance(inputs, (str, Path)) else list(inputs)
    res = prepare_files(paths, out, option="out=", quiet=not progress, object_triangles=object_triangles,
                        object_size=object_size, instance=instance, simplifier=simplifier, levels=levels, stream_mb=stream_mb,
                        crease_angle=CREASE_ANGLE if crease_angle is None else crease_angle, up=up, overwrite=overwrite)
    _warn(res.get("warnings", []))
    return res


def scene_info(store: str | Path) -> dict:
    """What ``massview info SCENE --json`` prints: objects, geometries, triangles, levels, the
    world box, disk use."""
    from .data.scene.verify import scene_info as info

    return info(Path(store))


def verify_scene(store: str | Path, progress: bool = False) -> list[str]:
    """The problems ``massview verify SCENE`` finds (every record decodes and matches its
    checksum, counts and the group tree agree); an empty list for a sound store."""
    from .app.terrain_cmds import progress_bar
    from .data.scene.verify import verify_scene as verify

    with progress_bar(not progress) as prog:
        return verify(Path(store), prog)
