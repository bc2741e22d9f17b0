"""Colours of trimesh meshes, and baking a texture into per-vertex colours (a scene store
keeps no textures).

A textured mesh (OBJ ``map_Kd``, glTF ``baseColorTexture``) is stored with one colour per
vertex, interpolated across each triangle: detail of the texture finer than the mesh's
vertices is lost, and ``prepare scene`` says so. Which colour a vertex gets matters when the
texture is finer than the mesh: the texel at the vertex's UV (what ``trimesh``'s ``to_color``
gives) is one sample of it — an 8×8 red/blue checker on a quad becomes a red–blue gradient —
while the texture's *mean over the vertex's faces* keeps the colour the surface shows on
average (the checker becomes purple). :func:`bake_vertex_colors` does the latter, the way a
GPU's mipmaps do:

1. each face's colour: the texel under its UV centroid in the *mip level* whose texels are
   about the face's size in the texture — level k holds the means of 2^k × 2^k texel blocks,
   k = round(log2 √(the UV triangle's area in texels)) (a face within one texel: level 0, the
   texel itself; textures repeat outside [0, 1), as with ``GL_REPEAT``);
2. each vertex's colour: the mean of its faces' colours weighted by their 3-D area (by count
   where they all have none). A vertex that no face uses gets the texel at its UV.

Deterministic (no randomness, no GPU); it costs one pass over the texture (the levels) and
one lookup per face.
"""

from __future__ import annotations

import numpy as np

__all__ = ["GREY", "bake_vertex_colors", "is_textured", "mip_levels", "texture_of", "trimesh_colors"]


def mip_levels(img: np.ndarray) -> list[np.ndarray]:
    """Levels (h_k, w_k, c) u8 of image ``img`` (h, w, c) u8: level 0 is ``img``, level k the
    means of its 2^k × 2^k blocks, rounded to nearest even (exact integer block sums: no error
    builds up from level to level; an odd last row or column is left out), down to one row or
    column."""
    out = [np.asarray(img, np.uint8)]
    s = out[0]  # block sums of the level last made
    while min(s.shape[:2]) >= 2:
        k = len(out)  # (sums of 4^k texels: uint16 holds level 1's, uint32 up to level 12's)
        dt = np.uint16 if k == 1 else np.uint32 if k <= 12 else np.uint64
        h, w = s.shape[0] // 2 * 2, s.shape[1] // 2 * 2
        s = s[0:h:2, 0:w:2].astype(dt) + s[1:h:2, 0:w:2] + s[0:h:2, 1:w:2] + s[1:h:2, 1:w:2]
        out.append(np.rint(s / 4.0 ** k).astype(np.uint8))
    return out


def _texel(levels: list[np.ndarray], k: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Texels (n, c) of mip levels ``levels`` at level ``k`` (n,) under ``uv`` (n, 2) (origin
    bottom left, repeated outside [0, 1)): the level-k block holding the level-0 texel."""
    h, w = levels[0].shape[:2]
    x = np.floor(np.mod(uv[:, 0], 1.0) * w).astype(np.int64) % w  # (x mod 1 of a tiny negative x is 1.0)
    y = h - 1 - np.floor(np.mod(uv[:, 1], 1.0) * h).astype(np.int64) % h  # row 0 at the top
    out = np.empty((len(uv), levels[0].shape[2]), np.uint8)
    for lv in np.unique(k):
        sel = k == lv
        a = levels[lv]
        out[sel] = a[np.minimum(y[sel] >> lv, a.shape[0] - 1), np.minimum(x[sel] >> lv, a.shape[1] - 1)]
    return out


def bake_vertex_colors(positions: np.ndarray, faces: np.ndarray, uv: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Per-vertex RGBA u8 (v, 4) of a textured mesh: positions (v, 3), faces (t, 3) int,
    per-vertex texture coordinates ``uv`` (v, 2), ``image`` (h, w, 4) u8 (row 0 at the top).
    See the module docstring for the rule."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    with np.errstate(over="ignore", invalid="ignore"):  # (coordinates beyond ±1e15 wrap to nonsense, as on a GPU)
        uv = np.clip(np.nan_to_num(np.asarray(uv, np.float64), nan=0.0), -1e15, 1e15)
    levels = mip_levels(image)
    out = _texel(levels, np.zeros(len(uv), np.int64), uv).astype(np.float64)  # (vertices no face uses keep their texel)
    if len(f) == 0:
        return out.astype(np.uint8)
    h, w = levels[0].shape[:2]
    tuv = uv[f]
    e1, e2 = tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0]
    texels = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) * w * h
    k = np.clip(np.rint(0.5 * np.log2(np.maximum(texels, 1e-300))), 0, len(levels) - 1).astype(np.int64)
    face = _texel(levels, k, tuv.mean(axis=1)).astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]), axis=1)
    idx = f.ravel()
    used = np.bincount(idx, minlength=len(p)) > 0
    for weight in (np.repeat(area, 3), np.ones(3 * len(f))):  # by area; by count where the faces have none
        total = np.bincount(idx, weight, len(p))
        sums = np.stack([np.bincount(idx, weight * np.repeat(face[:, c], 3), len(p)) for c in range(face.shape[1])], 1)
        ok = used & (total > 0)
        out[ok] = sums[ok] / total[ok, None]
        used &= ~ok
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


GREY = (200, 200, 200, 255)  # what a mesh without colours is drawn in


def texture_of(m) -> tuple[np.ndarray, np.ndarray] | None:
    """(RGBA image (h, w, 4) u8, per-vertex UVs (v, 2)) of a trimesh mesh whose material has a
    colour texture (``SimpleMaterial.image``: an OBJ's ``map_Kd``; ``PBRMaterial.baseColorTexture``:
    a glTF's), or None."""
    vis = m.visual
    if getattr(vis, "kind", None) != "texture":
        return None
    mat = getattr(vis, "material", None)
    img = getattr(mat, "baseColorTexture", None) if hasattr(mat, "baseColorTexture") else getattr(mat, "image", None)
    uv = getattr(vis, "uv", None)
    if img is None or uv is None or len(uv) != len(m.vertices):
        return None
    return np.asarray(img.convert("RGBA")), np.asarray(uv, np.float64)


def is_textured(m) -> bool:
    """``m`` (a trimesh mesh) has a colour texture that :func:`trimesh_colors` bakes."""
    try:
        return texture_of(m) is not None
    except Exception:  # noqa: BLE001 - an image PIL cannot convert: not baked (grey)
        return False


def trimesh_colors(m) -> np.ndarray:
    """Vertex colours (v,4) or corner colours (t,3,4) u8 of a trimesh mesh: its vertex or face
    colours, a texture baked by :func:`bake_vertex_colors`, a material's plain colour (an OBJ's
    ``Kd``, a glTF's ``baseColorFactor``), or :data:`GREY` when it has none (or trimesh cannot
    turn them into colours)."""
    vis = m.visual
    kind = getattr(vis, "kind", None)
    try:
        if kind == "texture":
            tex = texture_of(m)
            if tex is not None:
                return bake_vertex_colors(m.vertices, m.faces, tex[1], tex[0])
            mat = getattr(vis, "material", None)  # (trimesh's to_color made a glTF's plain colour one bad row: grey)
            plain = mat.baseColorFactor if hasattr(mat, "baseColorFactor") else getattr(mat, "main_color", None)
            if plain is not None:  # (a glTF material without a factor: grey, not trimesh's 40 % grey)
                return np.tile(np.asarray(plain, np.uint8)[:4], (len(m.vertices), 1))
        if kind == "vertex":
            return np.asarray(vis.vertex_colors, np.uint8)[:, :4]
        if kind == "face":
            return np.repeat(np.asarray(vis.face_colors, np.uint8)[:, None, :4], 3, axis=1)
    except Exception:  # noqa: BLE001 - a material trimesh cannot turn into colours: grey
        pass
    return np.tile(np.array(GREY, np.uint8), (len(m.vertices), 1))
