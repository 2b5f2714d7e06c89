"""Poison frames of registration: a frame whose registration fails max_deliveries times is rejected for good.

Every failure is counted per frame in Redis and the session is handed off to a fresh holder, which replays and
tries the frame again; at max_deliveries the frame is marked poison (registered as rejected from then on) and
dead-lettered.
"""

from __future__ import annotations

import logging

from services.jobs import dead_letters
from workers.config import Context
from workers.faults import failure_frames, failure_reason
from workers.stages.register.held import HeldSession

log = logging.getLogger("veinmosaic.worker")


class PoisonCounter:
    """Counts the registration failures of frames and dead-letters a frame that keeps failing."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx

    def registration_failed(self, held: HeldSession, seq: int, exc: Exception) -> None:
        """Count a registration failure of `seq`; after max_deliveries mark it poison; hand the session off."""
        ctx = self.ctx
        reason = failure_reason(exc)
        log.error("registration failed: %s\n%s", reason, failure_frames(exc), extra={"session": held.sid, "seq": seq})
        fails = dead_letters.count_registration_failure(ctx.r, held.sid, held.version, seq, ctx.prefix)
        if fails >= ctx.config.max_deliveries:
            ctx.results.mark_poison(held.sid, held.version, seq, f"registration failed: {type(exc).__name__}")
            entry = {
                "kind": "register-frame",
                "session": held.sid,
                "version": str(held.version),
                "seq": str(seq),
                "error": reason[:200],
            }
            dead_letters.dead_letter(ctx.r, entry, ctx.prefix)
        held.lease.release(ctx.r, mode="handoff", handoff_delay_s=0.5)  # a fresh holder retries
