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

Each rank ends with the final pixels of one region (maybe empty). ``deliver`` then moves
regions to display tiles: the destination rank (one tile covering the frame) or the ranks of
a display wall, each receiving only the pixels of its own tile.
"""

from __future__ import annotations

import numpy as np

from ..core.camera import Viewport
from ..core.errors import ConfigError
from ..core.image import Image, blank_image
from ..core.stats import FrameStats
from .codec import decode_image, encode_image
from .exchange import exchange

__all__ = ["COMPOSITORS", "combine", "split_rows", "radix_factors", "composite", "deliver"]

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


def _radix_rounds(comm, img: Image, members: list[int], factors: list[int], stats, codec, tag0: int) -> Image:
    idx = members.index(comm.Get_rank())
    current = img
    stride = 1
    for rnd, k in enumerate(factors):
        digit = (idx // stride) % k
        group = [members[idx + (j - digit) * stride] for j in range(k)]
        bands = split_rows(current.viewport, k)
        with stats.stage("encode"):
            sends = {group[j]: encode_image(current.crop(bands[j]), codec) for j in range(k) if j != digit}
        with stats.stage("transfer"):
            got = exchange(comm, sends, [g for j, g in enumerate(group) if j != digit], stats, tag0 + rnd)
        with stats.stage("composite"):
            acc = None
            for j in range(k):
                part = current.crop(bands[digit]) if j == digit else decode_image(got[group[j]])
                acc = part if acc is None else combine(acc, part)
        current = acc
        stride *= k
    return current


def composite(comm, img: Image, method: str = "binary-swap", k: int = 4, stats: FrameStats | None = None, codec: str = "blosc2") -> Image:
    """Sort-last depth compositing of every rank's full-frame ``img``. Returns the final pixels
    of the region this rank ends up owning (an empty viewport for ranks that own none)."""
    stats = stats if stats is not None else FrameStats(frame=-1, rank=comm.Get_rank())
    n, me = comm.Get_size(), comm.Get_rank()
    if n == 1:
        return img
    if method == "direct-send":
        return _radix_rounds(comm, img, list(range(n)), [n], stats, codec, 0)
    if method == "radix-k":
        return _radix_rounds(comm, img, list(range(n)), radix_factors(n, k), stats, codec, 0)
    if method != "binary-swap":
        raise ConfigError(f"unknown compositor {method!r}; use one of {', '.join(COMPOSITORS)}")
    p = 1 << (n.bit_length() - 1)
    extra = n - p
    if me < 2 * extra:  # fold pairs (2i, 2i+1) so that P ranks remain, in order
        if me % 2:
            with stats.stage("encode"):
                msg = {me - 1: encode_image(img, codec)}
            with stats.stage("transfer"):
                exchange(comm, msg, [], stats, 100)
            return Image(img.color[:0, :0], img.depth[:0, :0], Viewport(0, 0, 0, 0))
        with stats.stage("transfer"):
            got = exchange(comm, {}, [me + 1], stats, 100)
        with stats.stage("composite"):
            img = combine(img, decode_image(got[me + 1]))
    members = [r for r in range(n) if r >= 2 * extra or r % 2 == 0]
    return _radix_rounds(comm, img, members, [2] * (p.bit_length() - 1), stats, codec, 0)


def deliver(comm, piece: Image, tiles: list[tuple[int, Viewport]], stats: FrameStats | None = None, codec: str = "blosc2") -> Image | None:
    """Move final pixels to display tiles. ``piece`` is the region this rank holds (regions of
    all ranks partition the frame); ``tiles`` lists (display rank, tile viewport). Returns the
    assembled tile on display ranks, None elsewhere."""
    stats = stats if stats is not None else FrameStats(frame=-1, rank=comm.Get_rank())
    me = comm.Get_rank()
    regions = [Viewport.from_json(v) for v in comm.allgather(piece.viewport.to_json())]
    with stats.stage("encode"):
        sends = {}
        for rank, tile in tiles:
            part = piece.viewport.intersect(tile)
            if not part.empty:
                sends[rank] = encode_image(piece.crop(part), codec) if rank != me else piece.crop(part)
    my_tile = next((t for r, t in tiles if r == me), None)
    sources = [] if my_tile is None else [r for r, reg in enumerate(regions) if not reg.intersect(my_tile).empty]
    local = sends.pop(me, None)
    with stats.stage("transfer"):
        got = exchange(comm, sends, [s for s in sources if s != me], stats, 200)
    if my_tile is None:
        return None
    with stats.stage("composite"):
        out = blank_image(my_tile)
        if local is not None:
            out.paste(local)
        for s in sources:
            if s != me:
                out.paste(decode_image(got[s]))
    return out
