"""Which render options apply where, and how messages name them.

:func:`option_warnings` is the check behind ``massview render``/``view`` and
:func:`massview.render`: an option the user gave that the scene or system does not use
(``--exaggeration`` on a polygon scene, ``--compute-ranks`` without ``--system roettger``, ...)
gets one warning line naming it and why; one whose silent replacement would mislead
(``--system dmmr --decomposition sort-last``: M1 divides the screen, so it would run
``sort-first:balanced``) is a :class:`ConfigError`. Only options *given* are judged (a CLI flag
typed, an API keyword passed), never defaults.

Messages name options as CLI flags (``--tau``); :func:`keyword_text` rewrites them to the API's
keywords (``tau=``) for errors and warnings raised to Python callers.
"""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

from ..core.config import RenderConfig
from ..core.errors import ConfigError

__all__ = ["option_warnings", "keyword_text", "API_KEYWORDS"]

TERRAIN_SHADING = ("exaggeration", "sun", "colormap", "haze")
T2_OPTIONS = ("compute_ranks", "paper_partition", "triangle_budget", "roettger_C", "roettger_c", "fan_delta")
M1_OPTIONS = ("visible_frames", "query_threshold", "occlusion", "query_hierarchy", "occluder_lod", "stage_pipeline",
              "client_cache_mb", "record_ids", "id_check")
STORE_BUDGETS = ("tau", "cache_mb", "gpu_mb", "loading")  # a store's LOD and caches (builtin:objects has neither)
COMPOSITING = ("compositor", "radix_k")


def _flags(names) -> str:
    return ", ".join("--no-fan-delta" if n == "fan_delta" else f"--{n.replace('_', '-')}" for n in names)


M2_OPTIONS = ("tnz", "epsilon", "max_error", "size_threshold", "board_px", "min_triangles", "replicas", "placement_seed",
              "stall_backend", "tie_rule", "reference_every", "wait_boards")  # reliefboards_cmds.add_render_args' options


def no_effect_line(names, given, why: str) -> str | None:
    """The warning line for those of ``names`` in ``given`` (option names), or None."""
    hit = [n for n in names if n in given]
    return f"{_flags(hit)}: no effect {why}; leave {'it' if len(hit) == 1 else 'them'} out" if hit else None


HAZE_WARN = 4.0  # --haze above this washes a terrain out to the sky colour (walk5: 5 strongly faded, 50 a ghost)


def _has_orthophoto(spec: str) -> bool:
    """Whether the terrain store ``spec`` holds an orthophoto (its root attribute ``color``)."""
    from ..data.rebuild import store_attrs

    attrs = store_attrs(spec)
    return attrs is None or attrs.get("color") == "orthophoto"  # (unreadable: the store's own open names the problem)


def option_warnings(spec: str, kind: str, cfg: RenderConfig, given) -> list[str]:
    """Warning lines for the options in ``given`` (field names) that have no effect on scene
    ``spec`` of ``kind`` ("terrain", "scene", "objects") with ``cfg``'s system; ConfigError for
    ``--decomposition sort-last...`` given with ``--system dmmr``."""
    given = set(given)
    system = cfg.system
    if system == "dmmr" and "decomposition" in given and cfg.decomposition.startswith("sort-last"):
        raise ConfigError(f"--decomposition {cfg.decomposition}: --system dmmr (M1) divides the screen among its clients, it has no "
                          "sort-last mode; leave --decomposition out (Algorithm 1, reported as sort-first:balanced) or give "
                          "sort-first:horizontal, sort-first:vertical or sort-first:grid (equal tiles)")
    out = []

    def check(names, why: str) -> None:
        line = no_effect_line(names, given, why)
        if line:
            out.append(line)

    if kind != "terrain":
        check(TERRAIN_SHADING, f"on {spec}, a polygon scene (terrain shading and heights only)")
    if system != "roettger":
        check(T2_OPTIONS, "without --system roettger (T2 options" + ("; add it to use them" if kind == "terrain" else "") + ")")
    if system != "dmmr":
        check(M1_OPTIONS, "without --system dmmr (M1 options)")
    if system == "reliefboards":  # (walk8 M2: accepted silently, even a terrain's sort-last:kpatch)
        check(("decomposition", "wall"), "with --system reliefboards (its one visualization rank draws every frame whole; "
                                         "the others are board backends)")
    if kind == "objects" and system == "auto":
        check(STORE_BUDGETS, f"on {spec} (its objects are drawn whole from memory: no LOD, no block caches)")
    if kind == "terrain" and "colormap" in given and cfg.colormap == "ortho" and not _has_orthophoto(spec):
        out.append(f"--colormap ortho draws grey terrain here: {spec} has no orthophoto (prepare it with --color IMAGE)")
    if kind == "terrain" and "haze" in given and cfg.haze > HAZE_WARN:
        out.append(f"--haze {cfg.haze:g} hides most of the terrain in the sky colour (above {HAZE_WARN:g}; 0.5–2 reads as distance)")
    sort_first = cfg.decomposition.startswith("sort-first") or system in ("dmmr", "roettger", "reliefboards")
    if sort_first:
        what = f"with --system {system}" if system != "auto" else f"with --decomposition {cfg.decomposition}"
        check(COMPOSITING, f"{what} (no depth compositing: tiles are assembled)")
    return out


API_KEYWORDS = frozenset({f.name for f in fields(RenderConfig)} | {"size", "frames", "ranks", "out", "depth", "images"})
_VALUE_WORDS = frozenset({"auto", "roettger", "dmmr", "reliefboards", "on", "off", "async", "complete", "exact", "coarse",
                          "direct-send", "binary-swap", "radix-k", "none", "lz4", "blosc2", "ortho"})
_FLAG = re.compile(r"--([A-Za-z][\w-]*)(?: \((\w+)=\))?(?: ('[^']*'|\"[^\"]*\"|[\w.:+-]+))?")


def keyword_text(msg: str) -> str:
    """``msg`` with the CLI flags of API keywords written as keywords: ``--tau`` → ``tau=``,
    ``--size 'big'`` → ``size='big'``, ``--grid 2x2`` → ``grid=2x2``, ``--system roettger`` →
    ``system='roettger'``; other flags and words stay as they are."""
    def sub(m: re.Match) -> str:
        name = m.group(2) or m.group(1).replace("-", "_")
        if name == "no_fan_delta":
            return "fan_delta=False" + m.group(0)[len("--no-fan-delta"):]
        if name not in API_KEYWORDS:
            return m.group(0)
        value = m.group(3)
        if value is None:
            return f"{name}="
        if value[0] in "'\"":
            return f"{name}={value}"
        if re.search(r"\d", value) or value in _VALUE_WORDS or value.startswith(("sort-first", "sort-last")):
            v = value.rstrip(".,:;")
            tail = value[len(v):]
            plain = re.fullmatch(r"[\d.x:,+-]+", v) is not None
            return f"{name}={v if plain else repr(v)}{tail}"
        return f"{name}= {value}"

    return _FLAG.sub(sub, msg)
