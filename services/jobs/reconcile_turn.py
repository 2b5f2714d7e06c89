"""Whose turn it is to reconcile: a short lock (one reconciler at a time) and a key that spaces the periodic
runs across all workers (workers/reconciler.py decides when to ask)."""

from __future__ import annotations

import redis

from services.jobs.queue import reconcile_last_key, reconcile_lock_key

LOCK_TTL_MS = 60_000  # a reconciler that died holding the lock frees it after this long

_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""


def claim_periodic_run(r: redis.Redis, prefix: str, consumer: str, period_ms: int) -> bool:
    """Return True when no worker ran a periodic reconcile within period_ms, now marking this one's (SET NX PX)."""
    return bool(r.set(reconcile_last_key(prefix), consumer, nx=True, px=period_ms))


def mark_run(r: redis.Redis, prefix: str, consumer: str, period_ms: int) -> None:
    """Record an urgent run as the latest, so the periodic ones wait period_ms after it."""
    r.set(reconcile_last_key(prefix), consumer, px=period_ms)


def acquire_lock(r: redis.Redis, prefix: str, consumer: str) -> bool:
    """Return True when `consumer` now holds the reconcile lock (for LOCK_TTL_MS at most), False when another does."""
    return bool(r.set(reconcile_lock_key(prefix), consumer, nx=True, px=LOCK_TTL_MS))


def release_lock(r: redis.Redis, prefix: str, consumer: str) -> None:
    """Release the reconcile lock if `consumer` still holds it (never another worker's, taken after a timeout)."""
    r.eval(_RELEASE, 1, reconcile_lock_key(prefix), consumer)
