"""``--overwrite`` of a complete store without losing it until its replacement is whole.

Rebuilding a complete store used to remove it first: a prepare stopped half-way (Ctrl-C, a bad
input found late, a full disk) left an incomplete store where a good one had been. Now the new
store is built beside the old one (``OUT.rebuild``) and moved into its place only once it is
complete; the old one is then removed. If the build stops, the folder beside is removed and
the old store is untouched. The cost: room on disk for both while the new one is built.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Callable, TypeVar

from ..core.errors import StoreError

__all__ = ["store_attrs", "is_complete_store", "rebuild_beside"]

T = TypeVar("T")


def store_attrs(path) -> dict | None:
    """The root attributes of the zarr group at ``path`` ({} where it has none), or None where
    its ``zarr.json`` cannot be read as one."""
    try:
        return json.loads((Path(path) / "zarr.json").read_text()).get("attributes") or {}
    except (OSError, ValueError, AttributeError):
        return None


def is_complete_store(path, fmt: str) -> bool:
    """Whether ``path`` is a complete massview store of format ``fmt`` (its root attributes)."""
    a = store_attrs(path)
    return bool(a) and a.get("format") == fmt and bool(a.get("complete"))


def rebuild_beside(out, fmt: str, build: Callable[[Path], T]) -> T:
    """Run ``build(staging)`` to make a new store of format ``fmt`` at ``OUT.rebuild`` beside
    the complete store ``out``, then put it in ``out``'s place (the old store is removed after
    the swap). On any error or interrupt the staging folder is removed and ``out`` is left as
    it was. A leftover ``OUT.rebuild`` / ``OUT.replaced`` from an earlier stopped run is
    removed first when it is a store of that format, else it is an error naming it. An ``out``
    that is a symbolic link (a store kept on another disk) is rebuilt where the link points, and
    the link stays (a leftover link beside it is unlinked, never followed)."""
    out = Path(out)
    if out.is_symlink():
        out = out.resolve()
    staging, old = out.with_name(out.name + ".rebuild"), out.with_name(out.name + ".replaced")
    for p in (staging, old):
        if p.is_symlink():  # (left by an earlier version, which renamed the link itself)
            p.unlink()
        elif p.exists():
            if (store_attrs(p) or {}).get("format") != fmt:
                raise StoreError(f"{p} is in the way: --overwrite builds the new store there, beside {out}, and moves it into "
                                 "place when it is complete; move or remove that folder")
            shutil.rmtree(p)
    try:
        res = build(staging)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    os.rename(out, old)
    os.rename(staging, out)
    shutil.rmtree(old, ignore_errors=True)
    return res
