"""``massview upgrade STORE``: bring a terrain store written by an older massview to the
current format in place (exact LOD error bounds, shading pyramid; format 3's halos instead of
the stored level-0 shading), or repair a current store's halos; heights are untouched."""

from __future__ import annotations

import sys
import time

__all__ = ["add_parsers", "cmd_upgrade"]


def add_parsers(subparsers) -> None:
    p = subparsers.add_parser("upgrade", help="upgrade a terrain store from an older massview format in place (or rewrite damaged halos)")
    p.add_argument("store")
    p.add_argument("--quiet", "-q", action="store_true")


def cmd_upgrade(args) -> int:
    from ..data.terrain.upgrade import upgrade_store
    from .terrain_cmds import progress_bar

    t0 = time.perf_counter()
    with progress_bar(args.quiet) as prog:
        done = upgrade_store(args.store, prog)
    if not args.quiet:
        what = f"{done} in {time.perf_counter() - t0:.1f} s" if done else "is current already"
        print(f"terrain store {args.store}: {what}", file=sys.stderr)
    return 0
