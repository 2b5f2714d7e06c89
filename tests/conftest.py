"""Fixtures shared by every test folder: a real PACS (Orthanc, session-scoped; see tests/pacs_server.py); and the
skips summarised once per reason ("N tests need a Redis server: set REDIS_URL") rather than one line each."""

from __future__ import annotations

from collections import Counter
from typing import Any

from tests.pacs_server import Orthanc, orthanc

__all__ = ["Orthanc", "orthanc"]

REDIS_SKIP = "REDIS_URL not set"


def _reason(report: Any) -> str:
    longrepr = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:  # (path, line, "Skipped: reason")
        return str(longrepr[2]).removeprefix("Skipped: ")
    return str(longrepr)


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: Any) -> None:
    """Print each skip reason once with its count (pyproject's -r leaves skips out of the per-test summary)."""
    reasons = Counter(_reason(r) for r in terminalreporter.stats.get("skipped", []))
    if not reasons:
        return
    terminalreporter.section("skipped, by reason")
    for reason, n in reasons.most_common():
        if reason == REDIS_SKIP:
            terminalreporter.write_line(f"{n} tests need a Redis server: set REDIS_URL")
        else:
            terminalreporter.write_line(f"{n} skipped: {reason}")
