"""Command-line options of the massive-model system (``--system dmmr``, issue M1).

``add_dmmr_args`` adds its flags to ``render``/``view``; each flag's dest is the name of a
:class:`~massview.core.config.RenderConfig` field, which ``render_config`` maps by name.
"""

from __future__ import annotations

import argparse

__all__ = ["add_dmmr_args"]


def add_dmmr_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("massive models (--system dmmr: distributed massive model rendering; rank 0 server, other ranks clients)")
    g.add_argument("--visible-frames", type=int, default=None, help="dmmr: frames an object stays visible after passing a query (default 4)")
    g.add_argument("--query-threshold", type=int, default=None, help="dmmr: pixels a box must show to be visible (default 0)")
    g.add_argument("--occlusion", choices=("on", "off"), default=None, help="dmmr: occlusion culling on the clients (default on)")
    g.add_argument("--query-hierarchy", choices=("on", "off"), default=None,
                   help="dmmr: test query objects through the scene's group tree, culling a hidden group's objects with one query "
                        "(on, default: the same visible set, fewer queries) or with one query per object box (off, the paper's)")
    g.add_argument("--occluder-lod", choices=("exact", "coarse"), default=None,
                   help="dmmr: depth pre-pass at the rendered level (exact, default: conservative) or the coarsest level (the paper's)")
    g.add_argument("--stage-pipeline", choices=("on", "off"), default=None,
                   help="dmmr: divide frame i, cull i-1, render i-2 concurrently (default on); off = synchronous")
    g.add_argument("--client-cache-mb", type=int, default=None, help="dmmr: client RAM cache, MiB (default: the scene's object bytes / clients)")
    g.add_argument("--stage-delay", default=None, help=argparse.SUPPRESS)
    g.add_argument("--record-ids", action="store_true", default=None,
                   help="dmmr: each client's stats record lists the object ids it drew (drawn_ids)")
    g.add_argument("--id-check", action="store_true", default=None,
                   help="dmmr: clients also render an ID buffer of every object in their sub-frustum and record the ids it "
                        "shows (idbuffer_ids) and how many of them were not drawn (counter idbuffer_missed): the occlusion-culling check")
