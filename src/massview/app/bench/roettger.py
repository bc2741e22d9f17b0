"""``massview bench roettger`` (filled in below)."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("--workdir", default="out/bench/roettger")


def run(args) -> int:
    raise NotImplementedError
