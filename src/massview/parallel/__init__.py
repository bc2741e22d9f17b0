"""massview parallel layer."""
