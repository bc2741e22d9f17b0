"""Terrain data: the M-block pyramid store, its layout, inputs, ingest and metadata."""

from .ingest import PrepareResult, prepare_terrain
from .layout import BLOCK_SIZES, TerrainLayout
from .sources import ArraySource, RasterSource, open_source
from .store import FORMAT, FORMAT_VERSION, TerrainStore, dir_size

__all__ = ["TerrainLayout", "BLOCK_SIZES", "TerrainStore", "FORMAT", "FORMAT_VERSION", "dir_size",
           "RasterSource", "ArraySource", "open_source", "prepare_terrain", "PrepareResult"]
