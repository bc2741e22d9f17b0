"""The per-rank, per-frame task: which pixels to render and which part of the data to draw.

``viewport`` is the pixel rectangle the rank renders (the full frame for sort-last).
``data_range`` is a database range [a, b) ⊂ [0, 1) for sort-last; ``items`` an explicit list of
block or object ids; both None means "everything visible in the viewport".
"""

from __future__ import annotations

from dataclasses import dataclass

from .camera import Viewport
from .errors import ConfigError

__all__ = ["Task"]


@dataclass(frozen=True)
class Task:
    rank: int
    viewport: Viewport
    data_range: tuple[float, float] | None = None
    items: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.data_range is not None:
            a, b = (float(v) for v in self.data_range)
            if not 0.0 <= a <= b <= 1.0:
                raise ConfigError(f"Task data_range must satisfy 0 <= a <= b <= 1, got [{a}, {b})")
            object.__setattr__(self, "data_range", (a, b))
        if self.items is not None:
            object.__setattr__(self, "items", tuple(int(i) for i in self.items))

    def to_json(self) -> dict:
        return {
            "rank": self.rank,
            "viewport": self.viewport.to_json(),
            "data_range": list(self.data_range) if self.data_range else None,
            "items": list(self.items) if self.items is not None else None,
        }
