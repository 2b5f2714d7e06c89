"""Fixtures shared by every test folder: a real PACS (Orthanc, session-scoped; see tests/pacs_server.py)."""

from tests.pacs_server import Orthanc, orthanc

__all__ = ["Orthanc", "orthanc"]
