"""massview core layer."""
