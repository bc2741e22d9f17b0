"""T2's fan messages from a computation rank to a visualization rank (Gouranton et al. §3.2),
with only what changed since the previous frame (beyond the paper: its §5).

Per vertex the paper sends the index ``f = row · dim + col`` and the height: here uint32 and
float32 (8 bytes instead of 12 for (x, y, z); float32 indices are exact only below 2^24,
which a 4097² DEM already exceeds), with uint32 fan lengths. Both ends keep, per layer, the
list of fans the visualization rank holds from this computation rank, in the same order.
Each frame a layer's section carries:

    uint32 n_prev, n_new, n_vert_new
    keep bits: n_prev bits, packed, padded to 4 bytes   (1 = the held fan stays)
    uint32 lengths[n_new]; uint32 index[n_vert_new]; float32 height[n_vert_new]

and the held list becomes ``held[keep] + new``. A fan's identity is its centre sample and its
midpoint mask (a leaf's fan changes only when its neighbours change level). The message starts
with ``uint32 n_layers``. :class:`FanSender` and :class:`FanReceiver` are the two ends.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["FanSender", "FanReceiver", "HeldFans", "SectionStats", "encode_full", "decode_message"]


@dataclass
class SectionStats:
    """Bytes of one message: ``sent`` (delta encoding), ``full`` (all visible fans as index +
    height), ``xyz`` (all visible fans as float32 x, y, z) and fan counts."""

    sent: int = 0
    full: int = 0
    xyz: int = 0
    fans: int = 0
    new_fans: int = 0


def _offsets(lengths: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(np.asarray(lengths, np.int64))])


def _member(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.isin(a, b)`` for int64 keys by sort + binary search (several times faster than
    numpy's hash-based isin on a few 100 k keys)."""
    if len(b) == 0:
        return np.zeros(len(a), bool)
    sb = np.sort(b)
    i = np.minimum(np.searchsorted(sb, a), len(sb) - 1)
    return sb[i] == a


def _take(lengths: np.ndarray, arrays: list[np.ndarray], sel: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Fans ``sel`` (bool) of per-vertex ``arrays`` laid out by ``lengths``."""
    per_vertex = np.repeat(sel, np.asarray(lengths, np.int64))
    return lengths[sel], [a[per_vertex] for a in arrays]


class FanSender:
    """The computation-rank end for one visualization rank."""

    def __init__(self, layers: int):
        self.held = [np.zeros(0, np.int64) for _ in range(layers)]

    def encode(self, layers: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], delta: bool = True) -> tuple[bytes, SectionStats]:
        """``layers[k] = (keys int64 per fan, lengths uint32, index uint32, height float32)``
        of the fans this visualization rank sees now."""
        parts, st = [np.array([len(layers)], "<u4").tobytes()], SectionStats(full=4, xyz=4)
        for k, (keys, lengths, index, height) in enumerate(layers):
            prev = self.held[k]
            keys = np.asarray(keys, np.int64)
            keep = _member(prev, keys) if delta else np.zeros(len(prev), bool)  # no delta: drop all, resend all
            new = ~_member(keys, prev[keep]) if len(prev) else np.ones(len(keys), bool)
            nl, (ni, nh) = _take(np.asarray(lengths, np.uint32), [np.asarray(index, np.uint32), np.asarray(height, np.float32)], new)
            bits = np.packbits(keep.astype(np.uint8), bitorder="little")
            bits = np.concatenate([bits, np.zeros((-len(bits)) % 4, np.uint8)])
            parts += [np.array([len(prev), len(nl), len(ni)], "<u4").tobytes(), bits.tobytes(), nl.astype("<u4").tobytes(),
                      ni.astype("<u4").tobytes(), nh.astype("<f4").tobytes()]
            self.held[k] = np.concatenate([prev[keep], keys[new]])
            nv = int(np.asarray(lengths, np.int64).sum())
            st.full += 4 * len(keys) + 8 * nv + 12
            st.xyz += 4 * len(keys) + 12 * nv + 12
            st.fans += len(keys)
            st.new_fans += len(nl)
        msg = b"".join(parts)
        st.sent = len(msg)
        return msg, st


@dataclass
class HeldFans:
    """The fans a visualization rank holds from one computation rank for one layer."""

    lengths: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    height: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))


class FanReceiver:
    """The visualization-rank end for one computation rank."""

    def __init__(self, layers: int):
        self.held = [HeldFans() for _ in range(layers)]

    def apply(self, msg: np.ndarray | None) -> list[HeldFans]:
        """Apply one message; None (no message this frame) means nothing held, nothing new."""
        if msg is None:
            if any(len(h.lengths) for h in self.held):
                raise ValueError("no fan message although fans are held (the sender must send the drops)")
            return self.held
        for k, (keep, lengths, index, height) in enumerate(decode_message(msg)):
            h = self.held[k]
            if len(keep) != len(h.lengths):
                raise ValueError(f"fan message keeps {len(keep)} fans of layer {k}, {len(h.lengths)} are held")
            kl, (ki, kh) = _take(h.lengths, [h.index, h.height], keep)
            self.held[k] = HeldFans(np.concatenate([kl, lengths]), np.concatenate([ki, index]), np.concatenate([kh, height]))
        return self.held


def decode_message(msg) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(keep bool, lengths uint32, index uint32, height float32) per layer of one message."""
    buf = np.frombuffer(bytes(msg) if not isinstance(msg, np.ndarray) else msg.tobytes(), np.uint8)
    o = 0

    def u32(count):
        nonlocal o
        a = buf[o: o + 4 * count].view("<u4")
        o += 4 * count
        return a

    out = []
    (nlayers,) = u32(1)
    for _ in range(int(nlayers)):
        nprev, nnew, nvert = (int(v) for v in u32(3))
        nbytes = (nprev + 7) // 8
        keep = np.unpackbits(buf[o: o + nbytes], bitorder="little")[:nprev].astype(bool)
        o += nbytes + (-nbytes) % 4
        lengths = u32(nnew).copy()
        index = u32(nvert).copy()
        height = u32(nvert).view("<f4").copy()
        out.append((keep, lengths, index, height))
    return out


def encode_full(keys, lengths, index, height) -> bytes:
    """One layer's fans with nothing held (the first frame), for tests and tools."""
    return FanSender(1).encode([(keys, lengths, index, height)])[0]
