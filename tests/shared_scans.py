"""Where the shared reference scans are: ../shared/scans next to this checkout (absent on a bare clone)."""

from __future__ import annotations

from pathlib import Path

SHARED_SCANS = Path(__file__).resolve().parents[2] / "shared" / "scans"
