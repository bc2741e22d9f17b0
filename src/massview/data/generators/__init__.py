"""Deterministic procedural data: built-in scenes and synthetic terrains."""

from .objects import ObjectScene, generate_objects

__all__ = ["ObjectScene", "generate_objects"]
