"""Checks that an output folder or file can be written, before any work starts.

``--out /proc/x``, a read-only folder or a file where a folder should be end in one
:class:`~massview.core.errors.OutputError` naming the option and the path, before a rank
renders or a prepare reads its input — never in a traceback half-way through.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ..core.errors import ConfigError, OutputError

__all__ = ["check_output_dir", "check_output_file", "one_output"]


def _why(e: OSError) -> str:
    return e.strerror or type(e).__name__


def _probe(folder: Path, option: str, path: Path) -> None:
    try:
        fd, name = tempfile.mkstemp(prefix=".massview-probe-", dir=folder)
        os.close(fd)
        os.unlink(name)
    except OSError as e:
        raise OutputError(f"{option} {path}: cannot write in {folder} ({_why(e)}); choose a writable folder") from None


def check_output_dir(path: Path, option: str = "--out", create: bool = True) -> Path:
    """``path`` is (or, with ``create``, is made) a folder this process can write in."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{option} {path}: a file is in the way (the output must be a folder); remove it or choose another path")
    if not path.exists():
        if not create:
            return check_output_file(path, option)
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputError(f"{option} {path}: cannot create the folder ({_why(e)}); choose a writable location") from None
    _probe(path, option, path)
    return path


def check_output_file(path: Path, option: str = "output") -> Path:
    """The folder that will hold ``path`` exists (created if needed) and is writable, and
    ``path`` itself is not a folder unless it is to become one (stores), nor inside a massview
    (zarr) store, where it would be written among the store's arrays."""
    from ..data.scene.writer import enclosing_store

    path = Path(path)
    outer = enclosing_store(path)
    if outer is not None:
        raise ConfigError(f"{option} {path}: is inside the store {outer}; a store cannot hold another — choose a path outside it")
    parent = path.parent if str(path.parent) else Path(".")
    for p in [parent, *parent.parents]:
        if p.exists():
            if not p.is_dir():
                raise OutputError(f"{option} {path}: {p} is a file, not a folder; choose another path")
            break
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{option} {path}: cannot create {parent} ({_why(e)}); choose a writable location") from None
    _probe(parent, option, path)
    return path


def one_output(positional: str | None, option: str | None, usage: str) -> Path:
    """The output a ``generate`` command was given, positionally or as ``-o`` (the same path
    both ways is fine); none or two different ones is a :class:`ConfigError` (``usage``: how to
    give it, shown after "no output given; ")."""
    if positional and option and Path(positional) != Path(option):
        raise ConfigError(f"two outputs given ({positional} and -o {option}); give one")
    if not (positional or option):
        raise ConfigError(f"no output given; {usage}")
    return Path(option or positional)
