"""What comes in: the scan, its reference track, the study context and frame image headers."""
