"""massview: parallel out-of-core rendering of massive terrains and polygon models.

Layers (imports point down only): app → systems → parallel → render → lod → data → core.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
