"""Compiled per-sample kernels of the ingest's row passes (numba, cached, GIL released).

Each kernel replaces a chain of numpy expressions (and their full-size temporaries) by one
loop that performs, per sample, exactly the same float32 operations in the same order (no
fused multiply-add, no fast-math; scalars rounded to float32 first, as numpy 2 does with Python
floats), so the stores they produce are bit-identical (tests/test_ingest_parallel.py compares
whole stores with digests recorded before issue 20; tests/test_ingest_kernels.py compares every
kernel with the numpy expression it replaces):

* :func:`block_stats`: min, max and largest dropped-sample δ of a block
  (:func:`meta.vertex_deltas`) and the z-ranges of its patch squares (``DiamondAccumulator``);
  :func:`row_stats` runs it over a block row's strided blocks in one call;
* :func:`horn_row` / :func:`tent_row`: level-0 shading (:func:`horn_blocks`: the same, reading
  a block row's blocks in place of its wide rows) (Horn's slopes and the height fraction)
  and the [1 2 1]/4 mip step of :mod:`colors`, writing float16 with numpy's own rounding
  (:func:`f2h`: F16C's conversion where the CPU has it, else :func:`_half_bits`; numba has no
  float16 type on the CPU);
* :func:`all_finite`: the strip check of the prepare's fast read path;
* :func:`local_d2`: Röttger's local roughness (:func:`roettger.local_d2`);
* :func:`propagate_max`: Röttger's propagation of a depth into the next coarser one
  (:func:`roettger.propagate_into`, without its eight band-sized temporaries).

Inputs beyond the domain border are clamped (edge replication), as the numpy versions pad.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from .kernels import _jit

__all__ = ["block_stats", "row_stats", "horn_row", "horn_blocks", "horn_padded", "tent_row", "all_finite", "local_d2", "propagate_max", "half_lut", "to_half", "from_half", "h2f"]

_HALF = np.float32(0.5)
_QUART = np.float32(0.25)
_TWO = np.float32(2.0)


def half_lut() -> np.ndarray:
    """float16 bit pattern → float32 value, all 65 536 of them (exact)."""
    return np.arange(65536, dtype=np.uint32).astype(np.uint16).view(np.float16).astype(np.float32)


@_jit
def _half_bits(f):
    """IEEE float32 bits (uint32) → float16 bits, rounded to nearest even exactly as numpy's
    ``npy_floatbits_to_halfbits`` (overflow → ±inf, NaN stays NaN, subnormals rounded)."""
    f = np.int64(f)  # (signed 64-bit arithmetic throughout: no unsigned/signed promotion)
    h_sgn = (f & 0x80000000) >> 16
    f_exp = f & 0x7F800000
    if f_exp >= 0x47800000:
        if f_exp == 0x7F800000 and (f & 0x007FFFFF) != 0:
            ret = 0x7C00 + ((f & 0x007FFFFF) >> 13)
            return np.uint16(h_sgn + (ret + 1 if ret == 0x7C00 else ret))
        return np.uint16(h_sgn + 0x7C00)
    if f_exp <= 0x38000000:
        if f_exp < 0x33000000:
            return np.uint16(h_sgn)
        e = f_exp >> 23
        sig = (0x00800000 + (f & 0x007FFFFF)) >> (113 - e)
        if (sig & 0x3FFF) != 0x1000 or (f & 0x7FF) != 0:
            sig += 0x1000
        return np.uint16(h_sgn + (sig >> 13))
    h_exp = (f_exp - 0x38000000) >> 13
    sig = f & 0x007FFFFF
    if (sig & 0x3FFF) != 0x1000:
        sig += 0x1000
    return np.uint16(h_sgn + ((h_exp + (sig >> 13)) & 0xFFFF))


def _host_has_f16c() -> bool:
    try:
        import llvmlite.binding as llb

        return bool(llb.get_host_cpu_features().get("f16c", False))
    except Exception:  # noqa: BLE001 - no feature list: the software conversion
        return False


_F16C = _host_has_f16c()  # (numba's cache is keyed by the CPU's features, so a cached kernel matches it)


@intrinsic
def _f16_bits(typingctx, x):
    """float32 → float16 bits by LLVM's ``fptrunc`` (IEEE round to nearest even: F16C's
    ``vcvtps2ph`` where the CPU has it, vectorized): numpy's rounding for every non-NaN value
    (tests/test_ingest_kernels.py)."""
    if x != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))
    return types.uint16(types.float32), codegen


@intrinsic
def _f32_bits(typingctx, x):
    """The bits of a float32 as uint32 (a bit cast)."""
    if x != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))
    return types.uint32(types.float32), codegen


@intrinsic
def _h2f_bits(typingctx, x):
    """float16 bits → float32 by LLVM's ``fpext`` (exact; F16C's ``vcvtph2ps`` where the CPU
    has it, vectorized)."""
    if x != types.uint16:
        return None

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())
    return types.float32(types.uint16), codegen


@_jit
def h2f(bits, lut):
    """float16 bits (uint16) → float32, exactly: by the hardware where the CPU has F16C, else
    from ``lut`` (:func:`half_lut`)."""
    if _F16C:
        return _h2f_bits(bits)
    return lut[bits]


@_jit
def from_half(src, lut, dst):
    """float16 bits (uint16) array → float32, element by element, by :func:`h2f`."""
    s, d = src.ravel(), dst.ravel()
    for k in range(s.shape[0]):
        d[k] = h2f(s[k], lut)


@_jit
def f2h(v):
    """float32 → float16 bits (uint16) with numpy's rounding: by the hardware where the CPU
    has F16C, else by :func:`_half_bits`."""
    if _F16C:
        return _f16_bits(v)
    return _half_bits(_f32_bits(v))


@_jit
def to_half(src, dst, soft=False):
    """float32 array → float16 bits (uint16), element by element, by :func:`f2h` (or by the
    software :func:`_half_bits` when ``soft``)."""
    s, d = src.ravel(), dst.ravel()
    for k in range(s.shape[0]):
        d[k] = _half_bits(_f32_bits(s[k])) if soft else f2h(s[k])


@_jit
def block_stats(b, f, lo, hi):
    """(min, max, largest δ) of block ``b`` (M, M) float32 — δ of the square centres (parity
    of the local square index), horizontal and vertical edge midpoints, as
    :func:`meta.vertex_deltas` — and, when ``f`` > 0, the min/max of every closed f × f square
    into ``lo``/``hi`` ((M-1)/f)²."""
    return _stats_at(b, 0, 0, b.shape[0], f, lo, hi, 0)


@_jit
def _stats_at(w, r0, c0, M, f, lo, hi, q0):
    """:func:`block_stats` of the M × M block at (r0, c0) of ``w``; its squares go to the
    columns q0 .. of ``lo``/``hi``. Indices into ``w`` are unsigned (a signed offset keeps
    numba's negative-index wraparound on every read)."""
    u = np.uint64
    r0, c0 = u(r0), u(c0)
    mn, mx, dm = w[r0, c0], w[r0, c0], np.float32(0.0)
    if f == 0:  # (with z-ranges, the block's min/max are theirs: every sample lies in a square)
        for r in range(M):
            for c in range(M):
                v = w[r0 + u(r), c0 + u(c)]
                mn = min(mn, v)
                mx = max(mx, v)
    h = (M - 1) // 2
    for i in range(h + 1):
        for j in range(h + 1):
            y, x = r0 + u(2 * i), c0 + u(2 * j)
            y1, y2, x1, x2 = y + u(1), y + u(2), x + u(1), x + u(2)
            if i < h and j < h:
                if (i + j) % 2 == 0:
                    diag = (w[y, x] + w[y2, x2]) * _HALF
                else:
                    diag = (w[y, x2] + w[y2, x]) * _HALF
                dm = max(dm, abs(w[y1, x1] - diag))
            if j < h:
                dm = max(dm, abs(w[y, x1] - (w[y, x] + w[y, x2]) * _HALF))
            if i < h:
                dm = max(dm, abs(w[y1, x] - (w[y, x] + w[y2, x]) * _HALF))
    if f > 0:
        n = (M - 1) // f
        for a in range(n):
            for q in range(n):
                ya, xq = r0 + u(a * f), c0 + u(q * f)
                zl, zh = w[ya, xq], w[ya, xq]
                for r in range(f + 1):
                    for c in range(f + 1):
                        v = w[ya + u(r), xq + u(c)]
                        zl = min(zl, v)
                        zh = max(zh, v)
                lo[a, q0 + q], hi[a, q0 + q] = zl, zh
                mn, mx = min(mn, zl), max(mx, zh)
    return mn, mx, dm


@_jit
def row_stats(w, nb, M, dr, dc, f, lo, hi, mm, dm):
    """:func:`block_stats` of the ``nb`` M × M blocks of a block row, block j at (j·dr, j·dc)
    of the 2-D array ``w`` (a wide row (M, nb·(M-1)+1): dr = 0, dc = M-1; blocks stacked
    (nb·M, M): dr = M, dc = 0), read in place: (min, max) into ``mm[j]``, δ into ``dm[j]`` and,
    when ``f`` > 0, block j's square z-ranges into the columns j·n .. j·n+n-1 of ``lo``/``hi``
    (n, nb·n), n = (M-1)/f."""
    n = (M - 1) // f if f > 0 else 0
    for j in range(nb):
        mn, mx, d = _stats_at(w, j * dr, j * dc, M, f, lo, hi, j * n)
        mm[j, 0], mm[j, 1], dm[j] = mn, mx, d


@_jit
def _horn_px(up, mid, dn, c, W, dx8, dy8, zlo, rng, o):
    """One sample of :func:`horn_row` (column ``c``, neighbours clamped to the row)."""
    cl, cr = max(c - 1, 0), min(c + 1, W - 1)
    a, b_, c_ = up[cl], up[c], up[cr]
    d, f = mid[cl], mid[cr]
    g, h, i = dn[cl], dn[c], dn[cr]
    o[c, 0] = f2h(((c_ + _TWO * f + i) - (a + _TWO * d + g)) / dx8)
    o[c, 1] = f2h(((a + _TWO * b_ + c_) - (g + _TWO * h + i)) / dy8)
    o[c, 2] = f2h((mid[c] - zlo) / rng)


@_jit
def _horn_plane(up, mid, dn, dx8, dy8, zlo, rng, ch, q):
    """Channel ``ch`` of :func:`_horn_px` for columns 1 .. W-2 into the plane ``q`` (W-2,):
    no clamping, three input rows, one contiguous output (LLVM vectorizes it)."""
    if ch == 0:
        for k in range(q.shape[0]):
            q[k] = f2h(((up[k + 2] + _TWO * mid[k + 2] + dn[k + 2]) - (up[k] + _TWO * mid[k] + dn[k])) / dx8)
    elif ch == 1:
        for k in range(q.shape[0]):
            q[k] = f2h(((up[k] + _TWO * up[k + 1] + up[k + 2]) - (dn[k] + _TWO * dn[k + 1] + dn[k + 2])) / dy8)
    else:
        for k in range(q.shape[0]):
            q[k] = f2h((mid[k + 1] - zlo) / rng)


@_jit
def _horn_inner(up, mid, dn, dx8, dy8, zlo, rng, o, planes):
    """:func:`_horn_px` for columns 1 .. W-2 (``o`` starts at column 1): each channel as a
    plane (:func:`_horn_plane`), then interleaved into ``o``."""
    n = o.shape[0]
    for ch in range(3):
        _horn_plane(up, mid, dn, dx8, dy8, zlo, rng, ch, planes[ch, :n])
    for k in range(n):
        o[k, 0], o[k, 1], o[k, 2] = planes[0, k], planes[1, k], planes[2, k]


@_jit
def _horn_line(up, mid, dn, W, dx8, dy8, zlo, rng, o, planes):
    """One output row ``o`` (W, 3) of :func:`horn_row` from its three input rows."""
    _horn_px(up, mid, dn, 0, W, dx8, dy8, zlo, rng, o)
    if W > 2:
        _horn_inner(up, mid, dn, dx8, dy8, zlo, rng, o[1: W - 1], planes)
    if W > 1:
        _horn_px(up, mid, dn, W - 1, W, dx8, dy8, zlo, rng, o)


@_jit
def horn_row(above, cur, below, dx8, dy8, zlo, rng, out):
    """Level-0 shading of the wide rows ``cur`` (M, W) float32 with the global rows just above
    and below (W,): ``out`` (M, W, 3) uint16 = float16 bits of Horn's ∂h/∂x (east), ∂h/∂y
    (north) and (h − zlo)/rng; ``dx8`` = float32(8·dx) etc. (colors.horn_slopes)."""
    M, W = cur.shape
    planes = np.empty((3, max(W - 2, 1)), np.uint16)
    for r in range(M):
        up = above if r == 0 else cur[r - 1]
        dn = below if r == M - 1 else cur[r + 1]
        _horn_line(up, cur[r], dn, W, dx8, dy8, zlo, rng, out[r], planes)


@_jit
def horn_padded(p, dx8, dy8, zlo, rng, out):
    """:func:`horn_row` of one block given padded with the samples around it, ``p`` (M+2, M+2)
    float32, into ``out`` (M, M, 3) uint16: every sample through :func:`_horn_inner`, the
    expressions :func:`_horn_px` computes at a clamped border too, so a replicated pad gives
    what the wide row gives there."""
    M = p.shape[0] - 2
    planes = np.empty((3, M), np.uint16)
    for r in range(M):
        _horn_inner(p[r], p[r + 1], p[r + 2], dx8, dy8, zlo, rng, out[r], planes)


@_jit
def _gather_row(blocks, r, dst):
    """Grid row ``r`` of a block row (nb, M, M) as one wide row ``dst`` (nb·(M-1)+1,): what
    :func:`store.wide_row` makes of it, one row at a time (blocks share their border column); returns ``dst``."""
    nb, M = blocks.shape[0], blocks.shape[1]
    for j in range(nb):
        c0 = j * (M - 1)
        src = blocks[j, r]
        for c in range(M):
            dst[c0 + c] = src[c]
    return dst


@_jit
def horn_blocks(above, blocks, below, dx8, dy8, zlo, rng, out):
    """:func:`horn_row` of the wide rows a block row ``blocks`` (nb, M, M) float32 spans,
    read from the blocks: each grid row is gathered into one of three small wide rows (in
    cache), so the block row is never copied whole. The same values, the same operations."""
    nb, M = blocks.shape[0], blocks.shape[1]
    W = nb * (M - 1) + 1
    planes = np.empty((3, max(W - 2, 1)), np.uint16)
    rows = np.empty((3, W), np.float32)  # grid rows r-1, r, r+1 at r % 3 (rotating)
    _gather_row(blocks, 0, rows[0])
    for r in range(M):
        if r + 1 < M:
            _gather_row(blocks, r + 1, rows[(r + 1) % 3])
        up = above if r == 0 else rows[(r - 1) % 3]
        dn = below if r == M - 1 else rows[(r + 1) % 3]
        _horn_line(up, rows[r % 3], dn, W, dx8, dy8, zlo, rng, out[r], planes)


@_jit
def _tent3(x0, x1, x2):
    return x0 * _QUART + x1 * _HALF + x2 * _QUART


@_jit
def _padded_row(above, m0, m1, below, p):
    """Row ``p`` of the padded rows: global row 2i(M-1) - 1 + p (see :func:`tent_row`)."""
    M = m0.shape[0]
    if p == 0:
        return above[0]
    if p <= M - 1:
        return m0[p - 1]
    if p <= 2 * (M - 1):
        return m1[p - M]
    return below[p - 2 * M + 1]


@_jit
def _vtent(g0, g1, g2, lut, v):
    """v[k] = the [1 2 1]/4 tent of lut[g0[k]], lut[g1[k]], lut[g2[k]] (three rows' float16
    bits, flattened, converted by :func:`h2f`): :func:`tent_row`'s vertical step for every
    column and channel once (it took the odd columns twice)."""
    for k in range(v.shape[0]):
        v[k] = _tent3(h2f(g0[k], lut), h2f(g1[k], lut), h2f(g2[k], lut))


@_jit
def _htent_inner(v, o_r):
    """:func:`tent_row`'s horizontal step for the output columns 1 .. Wo-2 (no clamping)."""
    for o in range(1, o_r.shape[0] - 1):
        x = 2 * o
        o_r[o, 0] = f2h(_tent3(v[x - 1, 0], v[x, 0], v[x + 1, 0]))
        o_r[o, 1] = f2h(_tent3(v[x - 1, 1], v[x, 1], v[x + 1, 1]))
        o_r[o, 2] = f2h(_tent3(v[x - 1, 2], v[x, 2], v[x + 1, 2]))


@_jit
def tent_row(above, m0, m1, below, lut, out):
    """One block row of shading level l from level l-1's float16 wide rows (uint16 bits):
    ``above`` (1, W, 3) the global row just above, ``m0``/``m1`` (M, W, 3) block rows 2i and
    2i+1 (their first M-1 rows), ``below`` (2, W, 3) the next two global rows; ``out``
    (M, (W-1)/2+1, 3) uint16. The [1 2 1]/4 tent in both axes at the kept samples
    (colors.tent_decimate); ``lut`` = :func:`half_lut`."""
    M, W = m0.shape[0], m0.shape[1]
    Wo = out.shape[1]
    v = np.empty((W, 3), np.float32)
    for r in range(M):
        g0 = _padded_row(above, m0, m1, below, 2 * r)
        g1 = _padded_row(above, m0, m1, below, 2 * r + 1)
        g2 = _padded_row(above, m0, m1, below, 2 * r + 2)
        _vtent(g0.reshape(-1), g1.reshape(-1), g2.reshape(-1), lut, v.reshape(-1))  # every column's vertical tent once
        o_r = out[r]
        for o in (0, Wo - 1):  # the border columns, clamped (edge replication); the rest unclamped
            xl, xc, xr = max(2 * o - 1, 0), 2 * o, min(2 * o + 1, W - 1)
            for ch in range(3):
                o_r[o, ch] = f2h(_tent3(v[xl, ch], v[xc, ch], v[xr, ch]))
        _htent_inner(v, o_r)


@_jit
def all_finite(bits):
    """Whether every float32 of ``bits`` (their uint32 bit patterns, 1-D) is finite: none has
    the exponent field all ones (±inf, NaN). One pass, no temporary (``np.isfinite(a).all()``
    made a bool array of a strip's size); the exponent fields' maximum vectorizes."""
    top = np.uint32(0)
    for k in range(bits.shape[0]):
        top = max(top, bits[k] & np.uint32(0x7F800000))
    return top != np.uint32(0x7F800000)


@_jit
def local_d2(g, d, out):
    """Röttger's local d2 of the nodes of edge ``d`` over ``g`` (2a+1, 2b+1) float32 (heights
    every d/2 samples) into ``out`` (a, b) float32 (roettger.local_d2)."""
    a, b = out.shape
    fd = np.float32(d)
    for i in range(a):
        for j in range(b):
            c00, c01 = g[2 * i, 2 * j], g[2 * i, 2 * j + 2]
            c10, c11 = g[2 * i + 2, 2 * j], g[2 * i + 2, 2 * j + 2]
            ctr = g[2 * i + 1, 2 * j + 1]
            dev = abs(g[2 * i, 2 * j + 1] - (c00 + c01) * _HALF)
            dev = max(dev, abs(g[2 * i + 2, 2 * j + 1] - (c10 + c11) * _HALF))
            dev = max(dev, abs(g[2 * i + 1, 2 * j] - (c00 + c10) * _HALF))
            dev = max(dev, abs(g[2 * i + 1, 2 * j + 2] - (c01 + c11) * _HALF))
            dev = max(dev, abs(ctr - (c00 + c11) * _HALF))
            dev = max(dev, abs(ctr - (c01 + c10) * _HALF))
            out[i, j] = dev / fd


@_jit
def propagate_max(coarse, fine, q0, k):
    """:func:`roettger.propagate_into` (``q0`` = row0 // 2, ``k`` float32): each 2 × 2 group of
    ``fine`` times ``k`` max-merged into its coarse node (all four), the node above (top two),
    below (bottom two), left (left two) and right (right two), where inside ``coarse``. The
    same float32 products; maxima are exact in any order."""
    H, W = coarse.shape
    for i in range(fine.shape[0] // 2):
        r = q0 + i
        for j in range(fine.shape[1] // 2):
            tl, tr = fine[2 * i, 2 * j] * k, fine[2 * i, 2 * j + 1] * k
            bl, br = fine[2 * i + 1, 2 * j] * k, fine[2 * i + 1, 2 * j + 1] * k
            top, bottom = max(tl, tr), max(bl, br)
            if 0 <= r < H:
                coarse[r, j] = max(coarse[r, j], max(top, bottom))
                if j >= 1:
                    coarse[r, j - 1] = max(coarse[r, j - 1], max(tl, bl))
                if j + 1 < W:
                    coarse[r, j + 1] = max(coarse[r, j + 1], max(tr, br))
            if 0 <= r - 1 < H:
                coarse[r - 1, j] = max(coarse[r - 1, j], top)
            if 0 <= r + 1 < H:
                coarse[r + 1, j] = max(coarse[r + 1, j], bottom)
