"""The LOD stage's compiled kernels (numba, cached on disk, GIL released).

The K-patch cut (:mod:`massview.lod.kpatch_compiled`, the batched top in
:mod:`massview.lod.kpatch_top`) and the shading blocks a view samples
(:mod:`massview.lod.texlod`) as loops instead of a few hundred whole-array numpy calls a frame:
:func:`split_test` (sphere centres to camera space, the frustum planes, the projected error
bound; :meth:`massview.lod.kpatch_cut.View.test`), :func:`top_rule`, :func:`diamond_test`,
:func:`resident`, :func:`kept`, :func:`leaves`, :func:`square_children`,
:func:`edge_children`, and from :mod:`.frontkernel` and :mod:`.texkernel` (re-exported here)
:func:`top_kept_seeds`, :func:`head_records`, :func:`patch_records` and :func:`shading_blocks`.

Each performs exactly the float64 operations of the numpy path, per element, in the same order
(no fused multiply-add, no fast-math; sqrt and division are exact) and writes its lists in the
numpy path's order, so the front, the requests and the shading wants are the same bits —
tests/test_lod_kernel.py checks both paths against each other and the stage's recorded digests.
The float loops are written with selects rather than branches so that they vectorise.

They live in ``data/`` because numba is that layer's dependency (DESIGN.md: each heavy
dependency lives in one layer), as :mod:`massview.data.skykernel` does; :mod:`massview.lod.kernels`
loads them on a thread, so that no frame waits for numba (until they are ready the numpy path
gives the same cut).
"""

from __future__ import annotations

import numpy as np

from .frontkernel import head_records, patch_records, top_kept_seeds  # one module for the LOD stage's kernels
from .jit import cached_jit as _jit
from .texkernel import shading_blocks

__all__ = ["split_test", "top_rule", "top_kept_seeds", "diamond_test", "resident", "kept", "leaves", "square_children",
           "edge_children", "head_records", "patch_records", "shading_blocks"]


@_jit
def _min(a, b):
    """np.minimum of two floats (NaN propagates), as selects: the loops stay vectorisable."""
    m = a if a <= b else b
    return m if a == a else a


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
def _pixels(p0, p1, pz, ri, e, ux, uy, uz, f):
    """(pixel error, in front of the eye) of a sphere at camera-space (p0, p1, pz), radius ``ri``,
    world error ``e``: View.test's bound f·e·√((|u_x| + a|u_z|)² + (|u_y| + b|u_z|)²)/(z_c − r),
    or e·∞ for a sphere reaching behind the eye. Selects, not branches (vectorisable)."""
    zl = -pz - ri
    pos = zl > 0
    zz = zl if pos else 1.0
    a = (abs(p0) + ri) / zz * uz + ux
    b = (abs(p1) + ri) / zz * uz + uy
    g = np.sqrt(a * a + b * b) * f / zz
    return (g * e if pos else e * np.inf), pos


@_jit
def split_test(x, y, z, r, err, rot, t, side_a, side_c, near, far, u, uz, f, tau, crit, pix, code):
    """Fill ``crit`` (bool), ``pix`` (float64) and ``code`` (int8) for spheres at world
    (``x``, ``y``, ``z``) with radii ``r`` and world errors ``err`` (float64 (n,) each), as
    View.test returns them; the view's constants as View keeps them (``rot`` (3, 3), ``t`` (3,),
    ``side_a``/``side_c`` (4,) on x, x, y, y; ``u`` (2,): |u_x|, |u_y|)."""
    ux, uy = u[0], u[1]
    behind = 0
    for i in range(len(x)):
        ri = r[i]
        p0, p1, pz, m = _camera_planes(x[i], y[i], z[i], ri, rot, t, side_a, side_c, near, far)
        inside = m >= -ri
        code[i] = np.int8(inside) + np.int8(m >= ri)
        p, pos = _pixels(p0, p1, pz, ri, err[i], ux, uy, uz, f)
        behind += not pos
        pix[i] = p
        crit[i] = inside & (p > tau)
    if behind:  # View.test's branch for a batch with spheres reaching behind the eye: 0 · ∞ is 0
        for i in range(len(x)):  # (pixel errors become 0, flags follow)
            if pix[i] != pix[i]:
                pix[i] = 0.0
                crit[i] = (code[i] >= 1) & (0.0 > tau)


@_jit
def _height(z, base, vs, Z):
    """columns.heights of one stored height: base + Z·(z·vs − base), in its operation order."""
    return (np.float64(z) * vs - base) * Z + base


@_jit
def diamond_test(key, edge, j, sa, dx, mdy, zlo, zhi, r, err, base, vs, Z, rot, t, side_a, side_c, near, far, u, uz, f, tau,
                 ids, crit, pix, code, split, zw):
    """One walked depth's split test from the packed keys (kpatch_walk._step): each diamond's
    table index ``ids``, sphere centre (the lattice point times dx, −dy; the height the centre of
    the stored z-range ``zlo``/``zhi`` as world heights, 0 for edges outside the lattice), radius
    ``r``, world error (``err``·vs·Z), then :func:`split_test`'s ``crit``, ``pix``, ``code``, and
    ``split``: critical and complete (every half that exists inside the domain is present), and
    ``zw`` (2, n): the z-range as world heights (the Front's zmin, zmax of the diamond's halves).
    Three loops (spheres, test, split), each of which vectorises (one was 2× slower)."""
    n = len(key)
    xyz, rr, ee = np.empty((3, n)), np.empty(n), np.empty(n)
    _spheres(key, edge, j, sa, dx, mdy, zlo, zhi, r, err, base, vs, Z, ids, xyz, rr, ee, zw, split)
    split_test(xyz[0], xyz[1], xyz[2], rr, ee, rot, t, side_a, side_c, near, far, u, uz, f, tau, crit, pix, code)
    for i in range(n):
        split[i] &= crit[i]


@_jit
def _spheres(key, edge, j, sa, dx, mdy, zlo, zhi, r, err, base, vs, Z, ids, xyz, rr, ee, zw, complete):
    """:func:`diamond_test`'s spheres, errors, z-ranges and completeness (``edge``: the same for
    the whole batch; both kinds written with selects)."""
    M = (1 << 30) - 1
    n = 1 << j
    N = n + 1
    half = (1 << sa) >> 1
    for i in range(len(key)):
        k = key[i]
        uu = k & M
        vv = (k >> 30) & M
        o = (k >> 60) & 1 if edge else 0
        d = (o * N + vv) * N + uu if edge else (vv << j) | uu
        xi = (uu << sa) + (((1 - o) << (sa - 1)) if edge else half)  # edges: (u + ½(1 − o))·a, squares (u + ½)·a
        yi = (vv << sa) + ((o << (sa - 1)) if edge else half)
        complete[i] = _complete(uu, vv, o, k >> 61, edge, n)
        lo, hi = _height(zlo[d], base, vs, Z), _height(zhi[d], base, vs, Z)
        c = (lo + hi) / 2
        xyz[0, i] = np.float64(xi) * dx
        xyz[1, i] = np.float64(yi) * mdy
        xyz[2, i] = c if (not edge) | np.isfinite(lo) else 0.0  # columns.square_centre, edge_centre
        ids[i] = d
        zw[0, i] = lo
        zw[1, i] = hi
        rr[i] = r[d]
        ee[i] = np.float64(err[d]) * vs * Z


@_jit
def _complete(uu, vv, o, hb, edge, n):
    """Every half of the diamond that exists inside the domain is present (present halves
    ``hb``: 1, 2 or 3): both for squares, an edge's on the domain border only one."""
    w = vv if o == 0 else uu
    return hb == ((np.int64(w >= 1) + 2 * np.int64(w < n)) if edge else 3)


@_jit
def leaves(key, J, sa, dx, mdy, zlo, zhi, base, vs, Z, hh, rot, t, side_a, side_c, near, far):
    """kpatch_walk._leaves: at the deepest square level every present half is a patch, its
    code from the sphere around its z-range (radius √(((zhi − zlo)/2)² + ``hh``)). Returns
    what :func:`kept` returns."""
    M = (1 << 30) - 1
    n = len(key)
    a = 1 << sa
    ids, code, zw = np.empty(n, np.int64), np.empty(n, np.int8), np.empty((2, n))
    none = np.zeros(n, np.bool_)
    for i in range(n):
        k = key[i]
        u, v = k & M, (k >> 30) & M
        d = (v << J) | u
        lo, hi = _height(zlo[d], base, vs, Z), _height(zhi[d], base, vs, Z)
        dz = (hi - lo) / 2
        r = np.sqrt(dz * dz + hh)
        m = _camera_planes(np.float64((u << sa) + (a >> 1)) * dx, np.float64((v << sa) + (a >> 1)) * mdy, (lo + hi) / 2, r, rot, t,
                           side_a, side_c, near, far)[3]
        ids[i], zw[0, i], zw[1, i] = d, lo, hi
        code[i] = np.int8(m >= -r) + np.int8(m >= r)
    return kept(ids, key, code, none, none, zw)


@_jit
def top_rule(ok, crit, p0, p1, ex0, ex1, S, H0, H1):
    """kpatch_top.TopBatch.walk's rule over the batch (parents before children): ``S[i]`` (split)
    ⇔ ``ok[i]`` and each half is present exactly where it exists (``S[p0[i]]`` = ``ex0[i]``, …;
    ``S`` has size + 2 entries, the last two the False and True sentinels); ``H0``, ``H1``: the
    halves present. Returns the deferred splits (present halves of critical diamonds that do
    not split)."""
    size = len(ok)
    S[size] = False
    S[size + 1] = True
    for i in range(size):
        S[i] = ok[i] and S[p0[i]] == ex0[i] and S[p1[i]] == ex1[i]
    deferred = 0
    for i in range(size):
        a, b = S[p0[i]], S[p1[i]]
        H0[i], H1[i] = a, b
        deferred += np.int64(crit[i] & (not S[i])) * (np.int64(a) + np.int64(b))
    return deferred


@_jit
def kept(ids, key, code, crit, split, zw):
    """kpatch_walk._kept: the present halves of the diamonds that do not split, half-0 patches
    first — (half-0 count, ids, keys, codes, z-ranges (2, k)) — and the deferred splits."""
    n = len(key)
    sel = np.empty(2 * n, np.int64)
    c, deferred = 0, 0
    for i in range(n):  # written always, kept by advancing
        stay = (not split[i]) & ((key[i] >> 61 & 1) != 0)
        sel[c] = i
        c += stay
        deferred += stay & crit[i]
    n0 = c
    for i in range(n):
        stay = (not split[i]) & ((key[i] >> 62 & 1) != 0)
        sel[c] = i
        c += stay
        deferred += stay & crit[i]
    kid, kkey, kcode, kz = np.empty(c, np.int64), np.empty(c, np.int64), np.empty(c, np.int8), np.empty((2, c))
    for q in range(c):
        i = sel[q]
        kid[q], kkey[q], kcode[q] = ids[i], key[i], code[i]
        kz[0, q], kz[1, q] = zw[0, i], zw[1, i]
    return n0, kid, kkey, kcode, kz, deferred


@_jit
def _merge(mark, k0, id0, k1, id1, h1):
    """kpatch_cut.merge_halves and the keys it yields: ``k0`` (half-0 receivers) with half 1
    marked where ``id1`` also holds them, then the ``k1`` not in ``id0`` with bit ``h1``; ``mark``
    is left zeroed."""
    for i in range(len(id1)):
        mark[id1[i]] = 1
    out = np.empty(len(k0) + len(k1), np.int64)
    for i in range(len(id0)):
        out[i] = k0[i] | (np.int64(mark[id0[i]]) << 62)
    for i in range(len(id1)):
        mark[id1[i]] = 0
    for i in range(len(id0)):
        mark[id0[i]] = 1
    c = len(k0)
    for i in range(len(id1)):  # written always, kept by advancing
        out[c] = k1[i] | h1
        c += mark[id1[i]] == 0
    for i in range(len(id0)):
        mark[id0[i]] = 0
    return out[:c]


@_jit
def square_children(key, split, n, mark):
    """kpatch_walk._square_children of the diamonds ``key`` that ``split``: their 4 sides' keys,
    in its order."""
    M, ROW, O, H0, H1 = (1 << 30) - 1, 1 << 30, 1 << 60, 1 << 61, 1 << 62
    N = n + 1
    s = np.flatnonzero(split)
    q = len(s)
    k0, id0, k1, id1 = np.empty(2 * q, np.int64), np.empty(2 * q, np.int64), np.empty(2 * q, np.int64), np.empty(2 * q, np.int64)
    for c in range(q):
        k = key[s[c]]
        u, v = k & M, (k >> 30) & M
        base = (v << 30) | u
        w = v * N + u
        id0[c], id0[q + c] = w + N, w + (N * N + 1)
        id1[c], id1[q + c] = w, w + N * N
        k0[c], k0[q + c] = base + (ROW | H0), base + (1 | O | H0)
        k1[c], k1[q + c] = base | H1, base | (O | H1)
    return _merge(mark, k0, id0, k1, id1, 0)


@_jit
def _edge_kids(ks, o, want, dk, di, m):
    """kpatch_walk._edge_kids for the edges ``ks`` of orientation ``want``."""
    M, VU = (1 << 30) - 1, (1 << 60) - 1
    sel = np.flatnonzero(o == want)
    q = len(sel)
    keys, ids = np.empty(4 * q, np.int64), np.empty(4 * q, np.int64)
    ok = np.empty(4 * q, np.bool_)
    for c in range(q):
        k = ks[sel[c]]
        hb = k >> 61
        cc = (k & VU) << 1
        w = ((cc >> 30) * m) | (cc & M)
        for p in range(4):
            keys[p * q + c] = cc - dk[p]
            ids[p * q + c] = w - di[p]
            ok[p * q + c] = (hb & 1) != 0 if p < 2 else hb >= 2
    if q and not ok.all():
        keep = np.flatnonzero(ok)
        return keys[keep], ids[keep]
    return keys, ids


@_jit
def edge_children(ks, n, mark):
    """kpatch_walk.edge_children of split edges ``ks`` (orientation and present halves in their
    bits 60–62): the 4 squares around each midpoint, in its order."""
    ROW, H0, H1 = 1 << 30, 1 << 61, 1 << 62
    m = 2 * n
    o = (ks >> 60) & 1
    k0, id0 = _edge_kids(ks, o, 0, np.array([ROW, ROW - 1, 0, -1]), np.array([m, m - 1, 0, -1]), m)
    k1, id1 = _edge_kids(ks, o, 1, np.array([1, -ROW + 1, 0, -ROW]), np.array([1, -m + 1, 0, -m]), m)
    k0 |= H0
    return _merge(mark, k0, id0, k1, id1, H1)


@_jit
def resident(key, edge, d, nb, flat, off, crit, split, miss):
    """kpatch_walk._resident over a flat residency array: ``split`` (in place) further needs
    the blocks each present half's children draw from — ``flat[off + bi·nb + bj]`` (the index
    clipped to the array, as ``take(mode="clip")``), with (bi, bj) = (v ≫ d, u ≫ d), or for half 0
    of an edge the block above (o = 0) or left (o = 1) — and ``miss`` (2, n) flags, per half, the
    critical diamonds whose blocks are missing (to request)."""
    M = (1 << 30) - 1
    last = len(flat) - 1
    for i in range(len(key)):
        k = key[i]
        u, v, hb = k & M, (k >> 30) & M, k >> 61
        o = (k >> 60) & 1 if edge else 0
        r1 = flat[min(max(off + (v >> d) * nb + (u >> d), 0), last)]
        if edge:
            r0 = flat[min(max(off + ((v - 1 + o) >> d) * nb + ((u - o) >> d), 0), last)]
            h0, h1 = (hb & 1) != 0, (hb & 2) != 0
            miss[0, i] = crit[i] & h0 & (not r0)
            miss[1, i] = crit[i] & h1 & (not r1)
            split[i] = split[i] & (r0 | (not h0)) & (r1 | (not h1))
        else:  # every present square has a half: one block
            miss[0, i] = crit[i] & (not r1)
            split[i] = split[i] & r1

