"""Geometry of the terrain pyramid and of the K-patch diamonds over it (pure integer math).

Sample grid. The input has ``rows × cols`` samples; it is padded (at the outer border only)
to a square of ``S = 2^n + 1`` samples with ``n = L + m``, where ``M = 2^m + 1`` is the M-block
size and ``2^L`` blocks span one side at the finest level. Coordinates are integer sample
indices ``(row, col)`` of the finest level; below, x = col and y = row.

M-block pyramid. Level ``l`` (0 = finest) samples every ``2^l``-th finest sample; it has
``2^(L-l)`` × ``2^(L-l)`` blocks of M × M samples; block ``(l, i, j)`` holds the samples
``row = (i·(M-1) + r)·2^l``, ``col = (j·(M-1) + c)·2^l`` for ``r, c ∈ [0, M)`` — neighbouring
blocks share their border row/column. Coarse samples coincide with fine ones (decimation).

K-patch bintree (RASTeR; Bösch, Goswami, Pajarola 2009). The domain square is split along
its diagonal into two isosceles right triangles; every triangle splits at the midpoint of its
hypotenuse. With ``a_j = 2^(n-j)``:

* *square level j* triangles have axis-aligned legs of length ``a_j``; each pair sharing a
  hypotenuse forms a **square diamond** ``(j, v, u)`` — the square of side ``a_j`` at row v,
  col u; its split vertex is the square's centre. The diagonal runs from corner (u, v) to
  (u+1, v+1) when ``u + v`` is even, from (u+1, v) to (u, v+1) when odd (the 4-8 mesh rule);
* *diagonal level j* triangles have an axis-aligned hypotenuse of length ``a_j`` (an edge of
  the level-j square lattice); a pair forms an **edge diamond** ``(j, o, v, u)``: o = 0 the
  horizontal edge from (u, v) to (u+1, v), o = 1 the vertical edge from (u, v) to (u, v+1).

A triangle drawn as a K-patch (``K = 2^k + 1`` vertices along each edge) is its uniform
refinement 2k levels down: (K-1)² triangles. A square-level-j patch uses samples of spacing
``2^(J-j)``, a diagonal-level-j patch ``2^(J-j-1)``, with ``J = n - k`` the deepest square
level (patches there use the finest samples and never split). The resolution doubles every two
bintree levels. Patches whose spacing is coarser than the top block's use every
``2^(l-L)``-th sample of the top block.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ...core.errors import ConfigError

__all__ = ["TerrainLayout", "BLOCK_SIZES"]

BLOCK_SIZES = (129, 257, 513)


def _log2_exact(v: int, what: str) -> int:
    e = int(round(math.log2(v)))
    if 2**e != v:
        raise ConfigError(f"{what} must be 2^k + 1, got {v + 1}")
    return e


@dataclass(frozen=True)
class TerrainLayout:
    rows: int  # valid input samples
    cols: int
    M: int = 257  # M-block samples per side
    K: int = 17  # K-patch vertices per edge

    def __post_init__(self) -> None:
        if self.rows < 2 or self.cols < 2:
            raise ConfigError(f"a terrain needs at least 2 × 2 samples, got {self.rows} × {self.cols}")
        if self.M not in BLOCK_SIZES:
            raise ConfigError(f"--block must be one of {', '.join(map(str, BLOCK_SIZES))}, got {self.M}")
        k = _log2_exact(self.K - 1, "K")
        if not 1 <= k <= self.m - 2:
            raise ConfigError(f"K = {self.K} needs 3 ≤ K ≤ (M-1)/4 + 1 for M = {self.M}")
        del k

    # -- sizes --------------------------------------------------------------------------
    @property
    def m(self) -> int:
        return _log2_exact(self.M - 1, "M")

    @property
    def k(self) -> int:
        return _log2_exact(self.K - 1, "K")

    @property
    def L(self) -> int:
        """Top level: 2^L blocks per side at level 0; level L is one block."""
        need = max(math.ceil((max(self.rows, self.cols) - 1) / (self.M - 1)), 1)
        return max(0, math.ceil(math.log2(need)))

    @property
    def levels(self) -> int:
        return self.L + 1

    @property
    def n(self) -> int:
        return self.L + self.m

    @property
    def S(self) -> int:
        """Padded samples per side."""
        return 2**self.n + 1

    @property
    def J(self) -> int:
        """Deepest square level of the patch bintree."""
        return self.n - self.k

    def blocks(self, level: int) -> int:
        """Blocks per side at ``level``."""
        return 2 ** (self.L - level)

    def block_span(self, level: int) -> int:
        """Finest-sample units one block spans at ``level``."""
        return (self.M - 1) << level

    def block_origin(self, level: int, i: int, j: int) -> tuple[int, int]:
        s = self.block_span(level)
        return i * s, j * s

    def block_valid(self, level: int, i: int, j: int) -> bool:
        """Whether the block holds at least one input (non-padding) sample."""
        r0, c0 = self.block_origin(level, i, j)
        return r0 < self.rows and c0 < self.cols

    def square_side(self, j: int) -> int:
        return 2 ** (self.n - j)

    def square_draw_level(self, j: int) -> int:
        """Sample level used by a square-level-j patch (may exceed L: strided top block)."""
        return self.J - j

    def edge_draw_level(self, j: int) -> int:
        return self.J - j - 1

    def to_json(self) -> dict:
        return {"rows": self.rows, "cols": self.cols, "M": self.M, "K": self.K}
