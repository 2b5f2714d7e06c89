"""What a stage answers when its job cannot run yet (the loop puts the entry back after the delay): shared by the
stages (prepare, send) and the job loop (workers.jobs), so none imports another for it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Retry:
    """The job cannot run yet: put it back after delay_s."""

    delay_s: float
    reason: str
