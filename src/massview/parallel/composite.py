"""Depth compositing and image delivery.

Everything reuses one associative ``combine(front, back)``: per pixel, the nearer depth wins
and on equal depth the front operand (the lower rank) wins, so any grouping of ranks in order
gives the same image as compositing serially in rank order.

Sort-last compositors are instances of one radix-k exchange (Peterka et al., "A configurable
algorithm for parallel image-compositing applications", SC 2009): the ranks are arranged as a
mixed-radix number with digits k_1 × k_2 × ... = N; in round i each group of k_i ranks that
differ only in digit i splits its current region into k_i row bands and each member gathers
and combines one band from all members, in rank order.

* ``direct-send``: one round with k = N.
* ``binary-swap``: pairs (2i, 2i+1) first fold the ranks above the largest power of two P ≤ N
  (the odd one sends its whole image), then log2(P) rounds of k = 2.
* ``radix-k``: N factored into digits ≤ k (a prime factor larger than k is one digit).

Kernels work in place (issue 20): bands are encoded from views of the image, received
messages are combined into this rank's own band by their active-pixel runs without being
decoded to images (lower ranks' parts in front, nearest first, then higher ranks' — the same
pixels as combining in rank order), and the band lives in a per-thread scratch buffer reused
frame after frame. ``combine`` itself stays the reference the tests compare with.

Each rank ends with the final pixels of one region (maybe empty). ``deliver`` then moves
regions to display tiles: the destination rank (one tile covering the frame) or the ranks of
a display wall, each receiving only the pixels of its own tile.
"""

from __future__ import annotations

import threading

import numpy as np

from ..core.camera import Viewport
from ..core.errors import ConfigError
from ..core.image import Image, blank_image
from ..core.stats import FrameStats
from .codec import encode_image, encode_region, merge_into, paste_into
from .exchange import exchange

__all__ = ["COMPOSITORS", "combine", "split_rows", "radix_factors", "composite", "final_regions", "deliver"]

COMPOSITORS = ("direct-send", "binary-swap", "radix-k")


def combine(front: Image, back: Image) -> Image:
    """Depth-composite two images of the same viewport; ``front`` wins ties. Associative."""
    if front.viewport != back.viewport:
        raise ConfigError(f"combine needs equal viewports, got {front.viewport} and {back.viewport}")
    take = back.depth < front.depth
    color = np.where(take[..., None], back.color, front.color)
    depth = np.where(take, back.depth, front.depth)
    return Image(color, depth, front.viewport)


def split_rows(vp: Viewport, k: int) -> list[Viewport]:
    """``k`` row bands covering ``vp`` in order (some empty when vp has fewer than k rows)."""
    cuts = [vp.y + (vp.h * i) // k for i in range(k + 1)]
    return [Viewport(vp.x, cuts[i], vp.w, cuts[i + 1] - cuts[i]) for i in range(k)]


def radix_factors(n: int, k: int) -> list[int]:
    """Digits for radix-k over n ranks: each the largest divisor ≤ k of what remains, or the
    remaining prime itself when it has none."""
    if k < 2:
        raise ConfigError(f"radix-k needs k >= 2, got {k}")
    out, rest = [], n
    while rest > 1:
        d = next((d for d in range(min(k, rest), 1, -1) if rest % d == 0), None)
        if d is None:
            d = next(p for p in range(2, rest + 1) if rest % p == 0)
        out.append(d)
        rest //= d
    return out


def _band(img: Image, vp: Viewport) -> Image:
    """The row band ``vp`` of ``img`` as a view (bands span the full width: contiguous)."""
    rows = slice(vp.y - img.viewport.y, vp.y - img.viewport.y + vp.h)
    return Image(img.color[rows], img.depth[rows], vp)


_POOL = threading.local()


def _scratch(vp: Viewport) -> Image:
    """This thread's reusable accumulator buffer shaped to ``vp``: compositing writes into the
    same pages frame after frame (a fresh 1280×1024 image costs more in page faults than the
    whole combine). Valid until the next :func:`composite` call on this thread."""
    need = vp.w * vp.h
    buf = getattr(_POOL, "buf", None)
    if buf is None or buf[1].size < need:
        buf = _POOL.buf = (np.empty(4 * need, np.uint8), np.empty(need, np.float32))
    return Image(buf[0][: 4 * need].reshape(vp.h, vp.w, 4), buf[1][:need].reshape(vp.h, vp.w), vp)


def _owned(img: Image, owned: bool) -> Image:
    """``img`` itself when this rank owns its pixels, else a copy in the scratch buffer."""
    if owned:
        return img
    out = _scratch(img.viewport)
    np.copyto(out.color, img.color)
    np.copyto(out.depth, img.depth)
    return out


def _merge_round(own: Image, parts: list, digit: int) -> Image:
    """Combine received messages ``parts`` (rank order, ``parts[digit]`` unused) into ``own``
    in place: those of lower ranks in front (nearest first), then those of higher ranks."""
    for j in range(digit - 1, -1, -1):
        merge_into(own, parts[j], front=True)
    for j in range(digit + 1, len(parts)):
        merge_into(own, parts[j], front=False)
    return own


def _radix_rounds(comm, img: Image, members: list[int], factors: list[int], stats, codec, tag0: int, owned: bool = False) -> Image:
    idx = members.index(comm.Get_rank())
    current = img
    stride = 1
    for rnd, k in enumerate(factors):
        digit = (idx // stride) % k
        group = [members[idx + (j - digit) * stride] for j in range(k)]
        bands = split_rows(current.viewport, k)
        with stats.stage("encode"):
            sends = {group[j]: encode_region(current, bands[j], codec) for j in range(k) if j != digit}
        with stats.stage("transfer"):
            got = exchange(comm, sends, [g for j, g in enumerate(group) if j != digit], stats, tag0 + rnd)
        with stats.stage("composite"):
            current = _owned(_band(current, bands[digit]), owned or rnd > 0)
            _merge_round(current, [got.get(g) for g in group], digit)
        _count_touched(stats, "encode", (k - 1) * current.nbytes + sum(len(m) for m in sends.values()))
        _count_touched(stats, "composite", 2 * current.nbytes + sum(m.size for m in got.values()))
        stride *= k
    return current


def _tile_buffer(vp: Viewport, blank: bool) -> Image:
    if blank:
        return blank_image(vp)
    return Image(np.empty((vp.h, vp.w, 4), np.uint8), np.empty((vp.h, vp.w), np.float32), vp)


def _copy_region(out: Image, src: Image, vp: Viewport) -> None:
    """Copy the pixels of ``vp`` from ``src`` into ``out`` (both must contain ``vp``)."""
    def sl(img):
        return (slice(vp.y - img.viewport.y, vp.y - img.viewport.y + vp.h), slice(vp.x - img.viewport.x, vp.x - img.viewport.x + vp.w))
    np.copyto(out.color[sl(out)], src.color[sl(src)])
    np.copyto(out.depth[sl(out)], src.depth[sl(src)])


def _count_touched(stats, stage: str, nbytes: int) -> None:
    """Count the bytes a stage must read and write at the least into ``touched_<stage>``: the
    memory term of the floors of ``massview bench composite`` and ``bench frame``. Pixels are
    8 B each. encode: the pixels sent are read, the messages written; composite: the own
    band read and the result written, the messages read."""
    stats.count(f"touched_{stage}", nbytes)


def composite(comm, img: Image, method: str = "binary-swap", k: int = 4, stats: FrameStats | None = None, codec: str = "blosc2") -> Image:
    """Sort-last depth compositing of every rank's full-frame ``img`` (left unchanged). Returns
    the final pixels of the region this rank ends up owning (an empty viewport for ranks that own
    none) as a view of this thread's scratch buffer: valid until the next call on this thread
    (hand it to :func:`deliver` or copy it)."""
    stats = stats if stats is not None else FrameStats(frame=-1, rank=comm.Get_rank())
    n, me = comm.Get_size(), comm.Get_rank()
    if n == 1:
        return img
    members, factors, extra = _plan(n, method, k)
    if me < 2 * extra:  # fold pairs (2i, 2i+1) so that P ranks remain, in order
        if me % 2:
            with stats.stage("encode"):
                msg = {me - 1: encode_image(img, codec)}
            _count_touched(stats, "encode", img.nbytes + len(msg[me - 1]))
            with stats.stage("transfer"):
                exchange(comm, msg, [], stats, 100)
            return Image(img.color[:0, :0], img.depth[:0, :0], Viewport(0, 0, 0, 0))
        with stats.stage("transfer"):
            got = exchange(comm, {}, [me + 1], stats, 100)
        with stats.stage("composite"):
            img = _owned(img, False)
            merge_into(img, got[me + 1], front=False)
        _count_touched(stats, "composite", 2 * img.nbytes + got[me + 1].size)
    return _radix_rounds(comm, img, members, factors, stats, codec, 0, owned=me < 2 * extra)


def _plan(n: int, method: str, k: int) -> tuple[list[int], list[int], int]:
    """(members of the radix rounds, their digits, ranks folded away first) of ``method``."""
    if method == "direct-send":
        return list(range(n)), [n], 0
    if method == "radix-k":
        return list(range(n)), radix_factors(n, k), 0
    if method != "binary-swap":
        raise ConfigError(f"unknown compositor {method!r}; use one of {', '.join(COMPOSITORS)}")
    p = 1 << (n.bit_length() - 1)
    extra = n - p
    return [r for r in range(n) if r >= 2 * extra or r % 2 == 0], [2] * (p.bit_length() - 1), extra


def final_regions(n: int, method: str, k: int, vp: Viewport) -> list[Viewport]:
    """The region each of ``n`` ranks holds after :func:`composite` of full-frame images of
    ``vp`` (what :func:`deliver` would otherwise learn with an allgather): computed the way the
    rounds split it, so every rank knows all regions without a message."""
    if n == 1:
        return [vp]
    members, factors, _ = _plan(n, method, k)
    regions = [Viewport(0, 0, 0, 0)] * n
    for idx, rank in enumerate(members):
        current, stride = vp, 1
        for f in factors:
            current = split_rows(current, f)[(idx // stride) % f]
            stride *= f
        regions[rank] = current
    return regions


def deliver(comm, piece: Image, tiles: list[tuple[int, Viewport]], stats: FrameStats | None = None, codec: str = "blosc2",
            regions: list[Viewport] | None = None) -> Image | None:
    """Move final pixels to display tiles. ``piece`` is the region this rank holds (regions of
    all ranks partition the frame); ``tiles`` lists (display rank, tile viewport); ``regions``
    every rank's region when the caller knows them (:func:`final_regions`), else they are
    allgathered. Returns the assembled tile on display ranks, None elsewhere (on one rank whose
    one tile is the piece's viewport: the piece itself)."""
    stats = stats if stats is not None else FrameStats(frame=-1, rank=comm.Get_rank())
    me = comm.Get_rank()
    if comm.Get_size() == 1 and tiles == [(0, piece.viewport)]:
        return piece  # one rank, one tile: the image is the tile (no copy)
    if regions is None:
        regions = [Viewport.from_json(v) for v in comm.allgather(piece.viewport.to_json())]
    with stats.stage("encode"):
        sends = {}
        for rank, tile in tiles:
            part = piece.viewport.intersect(tile)
            if not part.empty:
                sends[rank] = encode_region(piece, part, codec) if rank != me else part
    my_tile = next((t for r, t in tiles if r == me), None)
    sources = [] if my_tile is None else [r for r, reg in enumerate(regions) if not reg.intersect(my_tile).empty]
    local = sends.pop(me, None)
    with stats.stage("transfer"):
        got = exchange(comm, sends, [s for s in sources if s != me], stats, 200)
    _count_touched(stats, "encode", piece.nbytes + sum(len(m) for m in sends.values()))
    if my_tile is None:
        return None
    with stats.stage("composite"):
        covered = sum(regions[r].intersect(my_tile).area for r in sources) == my_tile.area
        out = _tile_buffer(my_tile, blank=not covered)  # regions partition the frame: each pixel written once
        if local is not None:
            _copy_region(out, piece, local)
        for s in sources:
            if s != me:
                paste_into(out, got[s], fill=covered)
    _count_touched(stats, "composite", out.nbytes + sum(m.size for m in got.values()))
    return out
