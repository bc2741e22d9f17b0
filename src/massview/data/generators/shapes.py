"""Mesh primitives for the generated scenes: boxes, tubes, tanks, I-beams, domes, cones, blobs.

Every function returns ``(positions f8 (v,3), triangles i8 (t,3), normals f8 (v,3))`` in world
units. Surfaces of revolution are built around the +z axis and then oriented; flat faces have
their own vertices (hard edges), curved ones share them (smooth shading). :func:`merge` joins
parts into one part; :func:`orient` maps +z onto a direction.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["box", "tube", "tank", "ibeam", "dome", "cone", "blob", "merge", "orient", "Part"]

Part = tuple[np.ndarray, np.ndarray, np.ndarray]

_FACES = [((0, 1, 3, 2), (-1, 0, 0)), ((4, 6, 7, 5), (1, 0, 0)), ((0, 4, 5, 1), (0, -1, 0)),
          ((2, 3, 7, 6), (0, 1, 0)), ((0, 2, 6, 4), (0, 0, -1)), ((1, 5, 7, 3), (0, 0, 1))]


def box(lo, hi) -> Part:
    """Axis-aligned box with 24 vertices (a normal per face), 12 triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[(hi if (i >> 2) & 1 else lo)[0], (hi if (i >> 1) & 1 else lo)[1], (hi if i & 1 else lo)[2]] for i in range(8)])
    p, n, t = [], [], []
    for k, (q, nn) in enumerate(_FACES):
        p.append(corners[list(q)])
        n.append(np.tile(nn, (4, 1)))
        t += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
    return np.concatenate(p), np.array(t, np.int64), np.concatenate(n).astype(float)


def _grid(nu: int, nv: int, closed_u: bool = True) -> np.ndarray:
    """Triangles of an (nu+1) x (nv+1) vertex grid, rows along v."""
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * (nv + 1) + j
    b = a + nv + 1
    return np.stack([np.stack([a, a + 1, b], -1), np.stack([a + 1, b + 1, b], -1)], -2).reshape(-1, 3).astype(np.int64)


def _revolve(profile_r: np.ndarray, profile_z: np.ndarray, seg: int) -> Part:
    """Surface of revolution of the profile (r(s), z(s)) around +z, ``seg`` segments.
    Normals from the profile's tangent."""
    th = np.linspace(0, 2 * math.pi, seg + 1)
    r, z = np.asarray(profile_r, float), np.asarray(profile_z, float)
    dr, dz = np.gradient(r), np.gradient(z)
    ln = np.hypot(dr, dz)
    ln[ln == 0] = 1
    nr, nz = dz / ln, -dr / ln
    c, s = np.cos(th)[None, :], np.sin(th)[None, :]
    p = np.stack([r[:, None] * c, r[:, None] * s, np.broadcast_to(z[:, None], (len(r), seg + 1))], -1)
    n = np.stack([nr[:, None] * c, nr[:, None] * s, np.broadcast_to(nz[:, None], p.shape[:2])], -1)
    return p.reshape(-1, 3), _grid(len(r) - 1, seg), n.reshape(-1, 3)


def _disk(r: float, z: float, seg: int, up: bool) -> Part:
    th = np.linspace(0, 2 * math.pi, seg, endpoint=False)
    p = np.concatenate([[[0, 0, z]], np.stack([r * np.cos(th), r * np.sin(th), np.full(seg, z)], 1)])
    k = np.arange(seg)
    t = np.stack([np.zeros(seg, int), 1 + k, 1 + (k + 1) % seg], 1)
    if not up:
        t = t[:, ::-1]
    return p, t.astype(np.int64), np.tile([0, 0, 1.0 if up else -1.0], (seg + 1, 1))


def tube(length: float, r: float, seg: int = 16, rings: int = 4, caps: bool = True) -> Part:
    """Cylinder along +z from 0 to ``length``, capped."""
    z = np.linspace(0, length, rings + 1)
    parts = [_revolve(np.full(rings + 1, r), z, seg)]
    if caps:
        parts += [_disk(r, 0.0, seg, False), _disk(r, length, seg, True)]
    return merge(parts)


def tank(height: float, r: float, seg: int = 48, rings: int = 24) -> Part:
    """Vertical vessel: cylinder with hemispherical heads, z from 0 to ``height``."""
    a = np.linspace(-math.pi / 2, 0, rings // 4 + 2)[:-1]
    body = np.linspace(r, max(height - r, r + 1e-3), rings // 2)
    b = np.linspace(0, math.pi / 2, rings // 4 + 2)[1:]
    rr = np.concatenate([r * np.cos(a), np.full(len(body), r), r * np.cos(b)])
    zz = np.concatenate([r + r * np.sin(a), body, body[-1] + r * np.sin(b)])
    rr[0], rr[-1] = 0.0, 0.0
    return _revolve(rr, zz, seg)


def dome(r: float, seg: int = 48, rings: int = 24, bulb: float = 1.15) -> Part:
    """Onion dome on z = 0: a bulb of radius ``r`` widening to ``bulb``·r, with a finial."""
    s = np.linspace(0, 1, rings + 1)
    rr = r * np.sin(np.pi * s * 0.95) * (1 + (bulb - 1) * np.sin(np.pi * s)) * (1 - s) ** 0.3
    rr[0] = r
    zz = r * 1.6 * s
    rr[-1] = 0.0
    return _revolve(np.concatenate([[0.0], rr]), np.concatenate([[0.0], zz]), seg)


def cone(height: float, r: float, seg: int = 24, rings: int = 8) -> Part:
    """Cone on z = 0 (a conifer's crown), closed at the base."""
    zz = np.linspace(0, height, rings + 1)
    rr = r * (1 - zz / height)
    return merge([_revolve(rr, zz, seg), _disk(r, 0.0, seg, False)])


def blob(rx: float, ry: float, rz: float, nu: int = 24, nv: int = 48, seed: int = 0) -> Part:
    """Lumpy ellipsoid (a deciduous crown), centred on the origin; bumps from ``seed``."""
    rng = np.random.default_rng(seed)
    u = np.linspace(-math.pi / 2, math.pi / 2, nu + 1)[:, None]
    v = np.linspace(0, 2 * math.pi, nv + 1)[None, :]
    k = rng.integers(2, 6, 3)
    ph = rng.uniform(0, 2 * math.pi, 3)
    bump = 1 + 0.12 * np.sin(k[0] * v + ph[0]) * np.cos(k[1] * u + ph[1]) + 0.06 * np.sin(k[2] * (u + v) + ph[2])
    d = np.stack([np.cos(u) * np.cos(v), np.cos(u) * np.sin(v), np.sin(u) + 0 * v], -1) * bump[..., None]
    p = d * np.array([rx, ry, rz])
    t = _grid(nu, nv)
    from ..scene.mesh import vertex_normals

    pp = p.reshape(-1, 3)
    return pp, t, vertex_normals(pp, t).astype(float)


def ibeam(length: float, h: float, w: float, tf: float, tw: float) -> Part:
    """I-section girder along +z: two flanges and a web (three boxes, 36 triangles)."""
    return merge([box((-w / 2, -h / 2, 0), (w / 2, -h / 2 + tf, length)),
                  box((-w / 2, h / 2 - tf, 0), (w / 2, h / 2, length)),
                  box((-tw / 2, -h / 2 + tf, 0), (tw / 2, h / 2 - tf, length))])


def merge(parts) -> Part:
    ps, ts, ns, off = [], [], [], 0
    for p, t, n in parts:
        ps.append(p)
        ts.append(t + off)
        ns.append(n)
        off += len(p)
    return np.concatenate(ps), np.concatenate(ts), np.concatenate(ns)


def orient(part: Part, direction, origin=(0, 0, 0), spin: float = 0.0) -> Part:
    """Rotate ``part`` so +z points along ``direction`` (after spinning ``spin`` rad about z),
    then translate by ``origin``."""
    p, t, n = part
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    c, s = math.cos(spin), math.sin(spin)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    z = np.array([0, 0, 1.0])
    v = np.cross(z, d)
    cz = float(z @ d)
    if np.linalg.norm(v) < 1e-12:
        r = np.eye(3) if cz > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        r = np.eye(3) + vx + vx @ vx / (1 + cz)
    m = r @ rz
    return p @ m.T + np.asarray(origin, float), t, n @ m.T
