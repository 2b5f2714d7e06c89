"""Placing frames: vein maps, features, matching, direct alignment, the registrar and the pose graph."""
