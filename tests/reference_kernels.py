"""The compositing kernels as they were before the in-place rewrite (issue 20), kept verbatim
as the reference implementation: tests compare the new kernels with these bit for bit."""

from __future__ import annotations

import struct

import numpy as np

from massview.core.camera import Viewport
from massview.core.image import Image, blank_image
from massview.parallel.codec import _compress, _decompress

_HEADER = struct.Struct("<4s4i3I")
_MAGIC = b"MVI1"
CODECS = {"none": 0, "lz4": 1, "blosc2": 2}
_NAMES = {v: k for k, v in CODECS.items()}


def _active_runs(active: np.ndarray) -> np.ndarray:
    edges = np.flatnonzero(active[1:] != active[:-1]) + 1
    if active.size and active[0]:
        edges = np.concatenate([[0], edges])
    bounds = np.concatenate([[0], edges, [active.size]])
    return np.diff(bounds).astype(np.uint32)


def encode_image(img: Image, codec: str = "blosc2") -> bytes:
    vp = img.viewport
    depth = img.depth.reshape(-1)
    active = depth != np.float32(1.0)
    runs = _active_runs(active)
    color = np.ascontiguousarray(img.color).reshape(-1).view(np.uint32)[active]
    raw = runs.tobytes() + color.tobytes() + depth[active].tobytes()
    head = _HEADER.pack(_MAGIC, vp.x, vp.y, vp.w, vp.h, CODECS[codec], len(runs), int(active.sum()))
    return head + _compress(codec, raw)


def decode_image(data) -> Image:
    buf = memoryview(data).cast("B")
    magic, x, y, w, h, cid, nruns, nact = _HEADER.unpack_from(buf)
    vp = Viewport(x, y, w, h)
    raw = _decompress(_NAMES[cid], bytes(buf[_HEADER.size:]))
    runs = np.frombuffer(raw, np.uint32, nruns)
    img = blank_image(vp)
    if nact:
        flags = np.zeros(nruns, bool)
        flags[1::2] = True
        active = np.repeat(flags, runs)
        off = nruns * 4
        img.color.reshape(-1).view(np.uint32)[active] = np.frombuffer(raw, np.uint32, nact, off)
        img.depth.reshape(-1)[active] = np.frombuffer(raw, np.float32, nact, off + nact * 4)
    return img


def combine(front: Image, back: Image) -> Image:
    take = back.depth < front.depth
    color = np.where(take[..., None], back.color, front.color)
    depth = np.where(take, back.depth, front.depth)
    return Image(color, depth, front.viewport)


def composite_round(parts: list[Image]) -> Image:
    """One radix round on one rank as it was: decode every part, combine in rank order."""
    acc = None
    for part in parts:
        acc = part if acc is None else combine(acc, part)
    return acc
