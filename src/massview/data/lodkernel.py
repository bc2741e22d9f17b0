"""The K-patch split test's compiled kernel (numba, cached on disk, GIL released).

:func:`split_test` does in one pass over the spheres what
:meth:`massview.lod.kpatch_cut.View.test` does with a few dozen numpy calls: the sphere centres
to camera space, the six frustum planes against the radius, the projected error bound and the
split flag. It performs exactly the float64 operations of the numpy path, per element, in the
same order (no fused multiply-add, no fast-math; sqrt and division are exact), so its flags,
pixel errors and codes are the same bits — tests/test_lod_kernel.py checks both paths against
each other and tests/test_lod_stage.py the stage's digest. The numpy path costs several ns per
element and call (~1.2 ms a frame at 20 k front patches on a 2.1 GHz Xeon, mostly memory
passes); this one makes one.

It lives in ``data/`` because numba is that layer's dependency (DESIGN.md: each heavy dependency
lives in one layer), as :mod:`massview.data.skykernel` does. Loaded on a thread by
:func:`massview.lod.kpatch_cut.load_split_kernel`, so that no frame waits for numba: until it
is ready the numpy path gives the same cut.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["split_test", "planes"]


def _jit(fn):
    try:
        return njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True, boundscheck=False, error_model="numpy")(fn)


@_jit
def _min(a, b):
    """np.minimum of two floats (NaN propagates)."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@_jit
def _camera_planes(x, y, z, r, rot, t, side_a, side_c, near, far):
    """(p0, p1, pz, least plane distance) of one sphere: View.to_camera's sums
    ((r₀x + r₁y) + r₂z) + t and View._planes' minimum over the four side planes, far and near."""
    p0 = ((rot[0, 0] * x + rot[0, 1] * y) + rot[0, 2] * z) + t[0]
    p1 = ((rot[1, 0] * x + rot[1, 1] * y) + rot[1, 2] * z) + t[1]
    pz = ((rot[2, 0] * x + rot[2, 1] * y) + rot[2, 2] * z) + t[2]
    m = p0 * side_a[0] + pz * side_c[0]
    m = _min(m, p0 * side_a[1] + pz * side_c[1])
    m = _min(m, p1 * side_a[2] + pz * side_c[2])
    m = _min(m, p1 * side_a[3] + pz * side_c[3])
    m = _min(m, pz + far)
    m = _min(m, -pz - near)
    return p0, p1, pz, m


@_jit
def split_test(x, y, z, r, err, rot, t, side_a, side_c, near, far, u, uz, f, tau, crit, pix, code):
    """Fill ``crit`` (bool), ``pix`` (float64) and ``code`` (int8) for spheres at world
    (``x``, ``y``, ``z``) with radii ``r`` and world errors ``err`` (float64 (n,) each), as
    View.test returns them; the view's constants as View keeps them (``rot`` (3, 3), ``t`` (3,),
    ``side_a``/``side_c`` (4,) on x, x, y, y; ``u`` (2,): |u_x|, |u_y|)."""
    n = len(x)
    ux, uy = u[0], u[1]
    every = True
    for i in range(n):
        ri = r[i]
        p0, p1, pz, m = _camera_planes(x[i], y[i], z[i], ri, rot, t, side_a, side_c, near, far)
        inside = m >= -ri
        code[i] = np.int8(inside) + np.int8(m >= ri)
        zlo = -pz - ri
        if zlo > 0:
            a = (abs(p0) + ri) / zlo * uz + ux
            b = (abs(p1) + ri) / zlo * uz + uy
            g = np.sqrt(a * a + b * b) * f / zlo
            p = g * err[i]
        else:
            every = False
            p = err[i] * np.inf
        pix[i] = p
        crit[i] = inside and p > tau
    if not every:  # View.test's branch for spheres reaching behind the eye: 0 · inf is 0
        for i in range(n):
            if pix[i] != pix[i]:
                pix[i] = 0.0
                crit[i] = False


@_jit
def planes(x, y, z, r, rot, t, side_a, side_c, near, far, code):
    """``code`` (int8): View._planes' 0 outside a plane, 1 crossing, 2 inside all."""
    for i in range(len(x)):
        ri = r[i]
        m = _camera_planes(x[i], y[i], z[i], ri, rot, t, side_a, side_c, near, far)[3]
        code[i] = np.int8(m >= -ri) + np.int8(m >= ri)


@_jit
def head_records(rec_int, rec_flt, rec_bid, head_code, head, cols, zs, code, bid):
    """The batched top's kept halves: column k of records ``head`` into ``cols[k, :m]``,
    ``zs[k, :m]``, their block ids and codes (``head_code`` indexed modulo its length: half
    record size + i is diamond i's half 1), m = len(head)."""
    nc = len(head_code)
    for i in range(len(head)):
        h = head[i]
        for k in range(rec_int.shape[0]):
            cols[k, i] = rec_int[k, h]
        zs[0, i] = rec_flt[0, h]
        zs[1, i] = rec_flt[1, h]
        bid[i] = rec_bid[h]
        code[i] = head_code[h % nc]


@_jit
def patch_records(key, spans, verts, rec, m, cols, bid):
    """The integer Front columns and flat block ids of the walked patches ``key`` (packed
    (half 1 ≪ 62 | o ≪ 60 | v ≪ 30 | u), written from position ``m`` on) — kpatch_walk's
    _patch_records and block ids, one depth span at a time. ``spans`` (k, 9) int64 rows: begin,
    end, half-0 count, table row 16·t, side log2 a, block shift, the level shift L − block level,
    the block level's flat offset, and t; ``verts``/``rec``: the per-(depth, parity, half) tables."""
    M = (1 << 30) - 1
    for s in range(spans.shape[0]):
        b, e, n0, r0, sa, sh, ls, boff = spans[s, 0], spans[s, 1], spans[s, 2], spans[s, 3], spans[s, 4], spans[s, 5], spans[s, 6], spans[s, 7]
        c6, c7, c10 = rec[0, r0], rec[1, r0], rec[4, r0]
        for i in range(b, e):
            k = key[i]
            row = r0 + (4 if i - b >= n0 else 0)
            row |= (k & 1) | ((k >> 29) & 2) | ((k >> 57) & 8)
            x0 = (k & M) << sa
            y0 = ((k >> 30) & M) << sa
            j = m + i
            cols[0, j] = verts[0, row] + x0
            cols[1, j] = verts[1, row] + y0
            cols[2, j] = verts[2, row] + x0
            cols[3, j] = verts[3, row] + y0
            cols[4, j] = verts[4, row] + x0
            cols[5, j] = verts[5, row] + y0
            cols[6, j] = c6
            cols[7, j] = c7
            bi = (rec[2, row] + y0) >> sh
            bj = (rec[3, row] + x0) >> sh
            cols[8, j] = bi
            cols[9, j] = bj
            cols[10, j] = c10
            bid[j] = (bi << ls) + bj + boff
