"""The lease and the fence: a held session is served only while this worker's lease on it is alive and newest.

The lease is renewed at most every lease_ms / 3 (a forced renewal at most every lease_ms / 6), which also pushes
the watchdog kick forward. Before every durable write the holder checks its fence: its lease value still in
Redis, and the token in state.json not newer than its own (a newer holder wrote since). Losing either raises
LeaseLostError: the session is dropped from memory without writing.
"""

from __future__ import annotations

import contextlib
import logging
import time

import redis

from services.jobs.leases import Lease, acquire
from services.store.version_state import VersionState
from workers.config import Context
from workers.stages.register.held import HeldSession

log = logging.getLogger("veinmosaic.worker")


class LeaseLostError(Exception):
    """Another worker holds (or took) the session: stop without writing."""


class LeaseKeeper:
    """Takes, renews, fences and hands off the registration leases of this worker's sessions."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx

    def take(self, sid: str, version: int) -> Lease | None:
        """Return the lease of (sid, version), None while another worker holds it (its kick flag is set then)."""
        cfg = self.ctx.config
        return acquire(self.ctx.r, sid, version, cfg.consumer, cfg.lease_ms, self.ctx.prefix)

    @staticmethod
    def fenced_out(state: VersionState, lease: Lease) -> bool:
        """Return True when a newer holder wrote the version's state (its fence token is above the lease's)."""
        return state.fence > lease.token

    def renew_if_due(self, held: HeldSession, force: bool = False) -> None:
        """Renew the lease (and push the watchdog) when due; LeaseLostError when it is no longer ours."""
        cfg = self.ctx.config
        now = time.monotonic()
        if not force and now - held.clocks.renewed < cfg.lease_ms / 3000.0:
            return
        if force and now - held.clocks.renewed < cfg.lease_ms / 6000.0:
            return
        if now - held.clocks.renewed > 0.8 * cfg.lease_ms / 1000.0:  # a step ran nearly as long as the lease
            log.warning(
                "lease renewed %.1f s after the last renewal", now - held.clocks.renewed, extra={"session": held.sid}
            )
        watchdog = time.time() + 2.0 * cfg.lease_ms / 1000.0
        if not held.lease.renew(self.ctx.r, cfg.lease_ms, watchdog):
            raise LeaseLostError
        held.clocks.renewed = now

    def check_fence(self, held: HeldSession) -> None:
        """Raise LeaseLostError unless the lease is still ours and no newer holder wrote the state."""
        if self.fenced_out(held.sv.state(), held.lease) or not held.lease.held(self.ctx.r):
            raise LeaseLostError

    def idle(self, held: HeldSession, now: float) -> bool:
        """Return True when the cursor has not moved for linger_s (the session may be released)."""
        return now - held.clocks.progressed > self.ctx.config.linger_s

    def hand_off_after_fault(self, held: HeldSession) -> None:
        """Release the lease so another worker continues after a delay; with Redis down it simply expires."""
        cfg = self.ctx.config
        delay = min(cfg.fault_backoff_max_s, max(1.0, cfg.fault_backoff_first_s * 10))
        # with Redis down the lease simply expires; the watchdog kick (or the reconciler) wakes a new holder
        with contextlib.suppress(redis.RedisError, OSError):
            held.lease.release(self.ctx.r, mode="handoff", handoff_delay_s=delay)
