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
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, TypeVar

from ..core.errors import StoreError

__all__ = ["store_attrs", "is_complete_store", "rebuild_beside", "writing", "being_written", "one_writer"]

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


def _lock_path(out) -> Path:
    out = Path(out)
    if out.is_symlink():
        out = out.resolve()
    return out.with_name(f".{out.name}.lock")


@contextmanager
def writing(out):
    """Hold the store at ``out`` for one writer for the block (walk9 M3: two prepares into one
    output deleted each other's arrays, or one reported success for a store holding the other's
    input): an exclusive ``flock`` on the hidden file ``.NAME.lock`` beside it, removed at the
    end (a killed writer's lock dies with it). A second writer gets a StoreError at once. Where
    the lock file cannot be made (no such folder, read-only), the block runs unlocked and the
    write itself fails as before."""
    import fcntl

    lock = _lock_path(out)
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
        except OSError:
            fd = None
            break
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            who = os.pread(fd, 200, 0).decode(errors="replace").strip()
            os.close(fd)
            raise StoreError(f"{out} is being written by another massview right now ({who or 'another process'}); wait for it "
                             "to finish, or choose another output") from None
        try:
            if os.stat(lock).st_ino == os.fstat(fd).st_ino:  # (else a writer that just finished removed it: take the new one)
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    if fd is None:
        yield
        return
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {os.uname().nodename}\n".encode(), 0)
        yield
    finally:
        try:
            os.unlink(lock)
        except OSError:
            pass
        os.close(fd)


def being_written(out) -> bool:
    """Whether a writer holds the store at ``out`` now (:func:`writing`)."""
    import fcntl

    try:
        fd = os.open(_lock_path(out), os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(fd)


def one_writer(fn):
    """``fn(first, out, ...)`` (a store writer whose second argument, or ``out=``, is the store)
    run under :func:`writing` of that store."""
    import functools

    @functools.wraps(fn)
    def locked(*args, **kw):
        with writing(kw["out"] if "out" in kw else args[1]):
            return fn(*args, **kw)
    return locked
