"""Sending DICOM objects to a PACS: operator-configured destinations, DICOMweb STOW-RS and DIMSE C-STORE.

An adapter beside services.store and services.jobs: services.core never imports it. `destinations` is plain
data (no network library), so the settings can parse destinations without pulling in httpx or pynetdicom;
`send.send_objects` is the one entry point that talks to a PACS.
"""
