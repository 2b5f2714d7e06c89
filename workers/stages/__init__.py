"""The worker stages: prepare (one frame), register (a session under a lease; a package), reprocess (a results
version), send (a session's DICOM objects to a PACS)."""
