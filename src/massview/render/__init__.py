"""massview render layer."""
