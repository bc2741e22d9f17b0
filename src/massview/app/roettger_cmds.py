"""CLI commands of T2: ``massview prepare roettger STORE`` (the per-node Röttger table of an
existing store; new stores get it from ``prepare terrain``)."""

from __future__ import annotations

import argparse

__all__ = ["add_parsers", "cmd_prepare_roettger"]


def add_parsers(prepare_sub) -> None:
    """Add ``roettger`` under ``massview prepare``."""
    p = prepare_sub.add_parser("roettger", help="compute T2's per-node roughness table (d2) of an existing terrain store")
    p.add_argument("store", help="a complete terrain store")
    p.add_argument("--min-C", type=float, default=None,
                   help="smallest --roettger-C the table must support (propagation K = C/(2(C-1)); default 4)")
    p.add_argument("--quiet", "-q", action="store_true")


def cmd_prepare_roettger(args: argparse.Namespace) -> int:
    from ..data.terrain.roettger import DEFAULT_C_MIN, prepare_roettger
    from .terrain_cmds import progress_bar

    C = DEFAULT_C_MIN if args.min_C is None else args.min_C
    with progress_bar(args.quiet) as prog:
        meta = prepare_roettger(args.store, C, prog)
    if not args.quiet:
        print(f"wrote the Röttger table of {args.store}: {meta['depths']} depths, C_min {meta['C_min']:g}, K {meta['K']:.4f}")
    return 0
