"""massview data layer."""
