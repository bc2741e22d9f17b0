"""Benchmarks: ``massview bench NAME``. They print figures as ratios against a baseline measured
in the same run and never assert a time (tests assert correctness, benchmarks measure speed).

Each module exposes ``add_arguments(parser)`` (its flags) and ``run(args) -> int`` (exit status),
and is registered by one line in :data:`BENCHES`; ``massview bench`` builds its subcommands from
this registry (the first docstring line of a module is its help text).
"""

from __future__ import annotations

from . import composite, dmmr, frame, ingest, lod, memory, paraview, reliefboards, roettger, scene, scene_ingest, terrain

__all__ = ["BENCHES"]

BENCHES = {
    "composite": composite,
    "terrain": terrain,
    "ingest": ingest,
    "frame": frame,
    "paraview": paraview,
    "scene-ingest": scene_ingest,
    "scene": scene,
    "roettger": roettger,
    "reliefboards": reliefboards,
    "dmmr": dmmr,
    "lod": lod,
    "memory": memory,
}
