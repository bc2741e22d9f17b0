"""massview app layer."""
