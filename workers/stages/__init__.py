"""The worker stages: prepare (one frame), register (a session under a lease), reprocess (a results version)."""
