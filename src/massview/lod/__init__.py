"""massview lod layer."""
