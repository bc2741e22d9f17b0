"""Argument types the benches share: checked when the command line is parsed, so a bad value is
argparse's one-line error naming the option (exit 2) before any job starts, not a traceback
after a run. Each returns the text normalised ("2, 3" → "2,3"), so the benches that split it
later keep doing so."""

from __future__ import annotations

import argparse

from ...core.config import parse_size

__all__ = ["int_list", "positive", "at_least", "size", "choices_list", "terrain_store"]


def _int(v: str, what: str) -> int:
    try:
        return int(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{v.strip()!r} is not an integer ({what})") from None


def int_list(minimum: int = 1, extra: tuple[str, ...] = (), example: str = "2,3,4"):
    """Comma-separated integers ≥ ``minimum`` (and the words ``extra``), at least one."""
    def parse(text: str) -> str:
        items = [v.strip() for v in str(text).split(",") if v.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f"{text!r}: give at least one value, e.g. {example}")
        what = f"comma-separated integers ≥ {minimum}" + (f" or {', '.join(extra)}" if extra else "") + f", e.g. {example}"
        for v in items:
            if v in extra:
                continue
            if _int(v, what) < minimum:
                raise argparse.ArgumentTypeError(f"{v} is below {minimum} ({what})")
        return ",".join(items)
    return parse


def at_least(minimum: int):
    """One integer ≥ ``minimum``."""
    def parse(text: str) -> int:
        i = _int(text, f"an integer ≥ {minimum}")
        if i < minimum:
            raise argparse.ArgumentTypeError(f"{i} is below {minimum}")
        return i
    return parse


positive = at_least(1)


def size(text: str) -> str:
    """An image size WIDTHxHEIGHT (:func:`massview.core.config.parse_size`)."""
    try:
        parse_size(text)
    except Exception as e:  # ConfigError or ValueError, with its own words
        raise argparse.ArgumentTypeError(str(e).removeprefix("--size ")) from None
    return text


def choices_list(names: tuple[str, ...]):
    """Comma-separated words out of ``names``, at least one."""
    def parse(text: str) -> str:
        items = [v.strip() for v in str(text).split(",") if v.strip()]
        bad = [v for v in items if v not in names]
        if not items or bad:
            raise argparse.ArgumentTypeError(f"{text!r}: use comma-separated words out of {', '.join(names)}")
        return ",".join(items)
    return parse


def terrain_store(path, option: str = "store"):
    """``path`` as a Path when it is a terrain store, else the error ``render`` gives for it
    (naming what the folder or file is and how to make a store), or one saying it is another
    kind of scene: at the start, not inside a job or after a first part ran (walk12)."""
    from pathlib import Path

    from ...core.errors import ConfigError
    from ...systems import scene_kind

    kind = scene_kind(str(path))
    if kind != "terrain":
        raise ConfigError(f"{option} {path}: is {'the built-in objects scene' if kind == 'objects' else 'a polygon scene store'}, "
                          "not a terrain store; give a store made by `massview prepare terrain INPUT -o STORE`")
    return Path(path)
