"""Sub-image codec: skip the background as active-pixel runs, then a fast byte codec.

Wire format (little-endian)::

    header  <4s 4i 3I>  magic b"MVI1", viewport x y w h, codec id, run count, active count
    body    compressed( runs uint32[run count] | color uint8[active, 4] | depth float32[active] )

``codec="auto"`` (the default) picks per communicator (:func:`resolve_codec`): when every rank
runs on this node (the launcher says so: MPICH's ``MPI_LOCALNRANKS``, Open MPI's
``OMPI_COMM_WORLD_LOCAL_SIZE``, a Slurm allocation of one node) messages move through shared
memory at several GB/s, faster than any byte codec packs them, so sub-images travel as runs
without byte compression (``none``) and :func:`massview.parallel.composite.deliver` sends final
regions as raw rows straight into the display tile; otherwise ``blosc2``. Every rank of a job
decides the same way.

Runs alternate background/active starting with background, over the row-major pixels of the
viewport; a pixel is background when its depth is exactly 1.0. Only active pixels' color and
depth are stored. Byte codecs: ``blosc2`` (LZ4 + byte shuffle, level 1; ``auto``'s choice
between nodes: it packs a 1.3 MB band in 0.2 ms here against 1.8 ms for lz4.frame, at a better
ratio), ``lz4`` (lz4.frame) and ``none``. Each runs on one thread per rank (ranks share the cores).

Encoding writes runs, colors and depths straight into the wire buffer from views of the image
(no crop, no concatenation); receivers combine (:func:`merge_into`) or paste
(:func:`paste_into`) a message's active pixels directly into their own buffers, without
decoding it to a full image first (kernels in :mod:`.kernels`).
"""

from __future__ import annotations

import os
import struct

import numpy as np

from ..core.camera import Viewport
from ..core.errors import ConfigError, ParallelError
from ..core.image import BACKGROUND_RGBA, Image, blank_image
from . import kernels

__all__ = ["CODECS", "CODEC_CHOICES", "resolve_codec", "all_ranks_local", "encode_image", "encode_region", "encode_message", "decode_image",
           "decode_runs", "message_counts", "merge_into", "merge_decoded", "paste_into", "paste_decoded"]

_HEADER = struct.Struct("<4s4i3I")
_MAGIC = b"MVI1"
CODECS = {"none": 0, "lz4": 1, "blosc2": 2}
CODEC_CHOICES = ("auto", *CODECS)
_NAMES = {v: k for k, v in CODECS.items()}
_LOCAL_SIZE_VARS = ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE")
_BG32 = np.array(BACKGROUND_RGBA, np.uint8).view(np.uint32)[0]


def all_ranks_local(comm, env=None, world_size: int | None = None) -> bool:
    """True when every rank of ``comm`` runs on this node: a one-rank communicator, or a job
    whose launcher reports as many ranks on this node as the whole job has (``world_size``,
    default MPI_COMM_WORLD's). The same answer on every rank (a job spread over nodes has fewer
    local ranks than ranks on each of them); an unknown launcher counts as spread (the codec
    for a network is the safe choice)."""
    if comm.Get_size() == 1:
        return True
    env = os.environ if env is None else env
    if world_size is None:
        from mpi4py import MPI

        world_size = MPI.COMM_WORLD.Get_size()
    for var in _LOCAL_SIZE_VARS:
        if env.get(var, "").strip().isdigit():
            return int(env[var]) == world_size
    return env.get("SLURM_JOB_NUM_NODES", env.get("SLURM_NNODES", "")).strip() == "1"


def resolve_codec(comm, codec: str) -> tuple[str, bool]:
    """(byte codec of run-coded messages, whether final regions are delivered as raw rows) for
    ``codec`` on ``comm``: ``auto`` is (``none``, True) when :func:`all_ranks_local`, else
    (``blosc2``, False); a named codec is itself, run-coded everywhere."""
    if codec == "auto":
        return ("none", True) if all_ranks_local(comm) else ("blosc2", False)
    if codec not in CODECS:
        raise ConfigError(f"unknown image codec {codec!r}; use one of {', '.join(CODEC_CHOICES)}")
    return codec, False


def _blosc2():
    import blosc2

    if blosc2.nthreads != 1:  # ranks share the cores; one codec thread per rank
        blosc2.set_nthreads(1)
    return blosc2


def _compress(codec: str, raw: bytes) -> bytes:
    if codec == "lz4":
        import lz4.frame

        return lz4.frame.compress(raw, compression_level=0, store_size=True)
    if codec == "blosc2":
        blosc2 = _blosc2()
        return blosc2.compress(raw, typesize=4, clevel=1, codec=blosc2.Codec.LZ4, filter=blosc2.Filter.SHUFFLE)
    return raw


def _decompress(codec: str, body: bytes) -> bytes:
    if codec == "lz4":
        import lz4.frame

        return lz4.frame.decompress(body)
    if codec == "blosc2":
        return _blosc2().decompress(body)
    return body


def _views(img: Image, vp: Viewport) -> tuple[np.ndarray, np.ndarray, Viewport]:
    """2-D views (depth float32, color uint32) of the part of ``img`` inside ``vp``; no copy."""
    v = img.viewport.intersect(vp)
    rows = slice(v.y - img.viewport.y, v.y - img.viewport.y + v.h)
    cols = slice(v.x - img.viewport.x, v.x - img.viewport.x + v.w)
    return img.depth[rows, cols], img.color[rows, cols].view(np.uint32)[..., 0], v


def encode_region(img: Image, vp: Viewport, codec: str = "blosc2") -> bytes:
    """Encode the part of ``img`` inside ``vp`` (destination pixels) without cropping it first:
    runs, colors and depths are written into the wire buffer in place."""
    return bytes(encode_message(img, vp, codec))


def encode_message(img: Image, vp: Viewport, codec: str = "blosc2", dense_above: float | None = None):
    """:func:`encode_region` as compositing sends it: with codec ``none`` one uint8 array, the
    header packed in place in front of the body (no copy of the body); else bytes. With
    ``dense_above``, a region whose share of active pixels exceeds it is sent with every pixel
    active (:func:`kernels.pack_dense`: the same format and the same combined pixels, a copy
    instead of a scan — on one node, where bytes are cheap)."""
    if codec not in CODECS:
        raise ConfigError(f"unknown image codec {codec!r}; use one of {', '.join(CODECS)}")
    depth, color, v = _views(img, vp)
    head = _HEADER.size if codec == "none" else 0
    active = depth != np.float32(1.0) if dense_above is not None else None  # computed once: pack_runs takes it
    if active is not None and depth.size > 0 and np.count_nonzero(active) > dense_above * depth.size:
        raw, nruns, nact = kernels.pack_dense(depth, color, head)
    else:
        raw, nruns, nact = kernels.pack_runs(depth, color, head, active)
    if codec == "none":
        _HEADER.pack_into(raw, 0, _MAGIC, v.x, v.y, v.w, v.h, CODECS[codec], nruns, nact)
        return raw
    return _HEADER.pack(_MAGIC, v.x, v.y, v.w, v.h, CODECS[codec], nruns, nact) + _compress(codec, raw)


def encode_image(img: Image, codec: str = "blosc2") -> bytes:
    """The wire message of a whole :class:`Image` (format in the module docstring)."""
    return encode_region(img, img.viewport, codec)


def message_counts(data) -> tuple[int, int]:
    """(pixels of the viewport, active pixels) of a message, from its header alone."""
    _, _, _, w, h, _, _, nact = _HEADER.unpack_from(memoryview(data).cast("B"))
    return w * h, nact


def decode_runs(data) -> tuple[Viewport, np.ndarray, np.ndarray, np.ndarray]:
    """(viewport, runs uint32, active colors uint32, active depths float32) of a message; the
    arrays are views of one decompressed buffer."""
    buf = memoryview(data).cast("B")
    if len(buf) < _HEADER.size:
        raise ParallelError(f"image message too short ({len(buf)} bytes)")
    magic, x, y, w, h, cid, nruns, nact = _HEADER.unpack_from(buf)
    if magic != _MAGIC or cid not in _NAMES:
        raise ParallelError("image message has a bad header (not a massview sub-image)")
    raw = _decompress(_NAMES[cid], buf[_HEADER.size:])
    if len(raw) != nruns * 4 + nact * 8:
        raise ParallelError(f"image message body is {len(raw)} bytes, header says {nruns * 4 + nact * 8}")
    runs = np.frombuffer(raw, np.uint32, nruns)
    if int(runs.sum(dtype=np.int64)) != w * h or int(runs[1::2].sum(dtype=np.int64)) != nact or (nruns > 1 and not runs[1::2].all()):
        raise ParallelError("image message runs do not cover its viewport (corrupt message)")
    off = nruns * 4
    return Viewport(x, y, w, h), runs, np.frombuffer(raw, np.uint32, nact, off), np.frombuffer(raw, np.float32, nact, off + nact * 4)


def decode_image(data) -> Image:
    vp, runs, color, depth = decode_runs(data)
    img = blank_image(vp)
    kernels.paste_runs(runs, color, depth, img.color.view(np.uint32)[..., 0], img.depth)
    return img


def merge_into(acc: Image, data, front: bool) -> None:
    """Depth-combine the message ``data`` (same viewport as ``acc``) into ``acc`` in place:
    ``combine(part, acc)`` when ``front`` (the part is from a lower rank), else
    ``combine(acc, part)`` — bit for bit, without decoding to a full image."""
    merge_decoded(acc, decode_runs(data), front)


def merge_decoded(acc: Image, part: tuple, front: bool) -> None:
    """:func:`merge_into` of a message already taken apart by :func:`decode_runs`."""
    vp, runs, color, depth = part
    if vp != acc.viewport:
        raise ParallelError(f"cannot combine a {vp} sub-image into {acc.viewport}")
    kernels.merge_runs(runs, color, depth, acc.color.view(np.uint32)[..., 0], acc.depth, front)


def paste_into(out: Image, data, fill: bool = False) -> None:
    """Write the message's pixels into ``out`` (its viewport must lie inside ``out``'s): the
    active ones, and with ``fill`` the background ones too (else those are left as they are)."""
    paste_decoded(out, decode_runs(data), fill)


def paste_decoded(out: Image, part: tuple, fill: bool = False) -> None:
    """:func:`paste_into` of a message already taken apart by :func:`decode_runs`."""
    vp, runs, color, depth = part
    if vp.empty:
        return
    if vp.intersect(out.viewport) != vp:
        raise ParallelError(f"sub-image {vp} does not lie inside the tile {out.viewport}")
    d, c, _ = _views(out, vp)
    if fill:
        d.fill(np.float32(1.0))
        c.fill(_BG32)
    kernels.paste_runs(runs, color, depth, c, d)
