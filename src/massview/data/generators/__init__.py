"""Deterministic procedural data: built-in scenes and synthetic terrains."""

from .objects import ObjectScene, generate_objects
from .terrain import SYNTHETIC_SPACING, synthetic_heights

__all__ = ["ObjectScene", "generate_objects", "synthetic_heights", "SYNTHETIC_SPACING"]
