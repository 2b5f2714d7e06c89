"""Per-key quotas of sessions and frames: how many a key (an owner, its fingerprint) may create per window.

Fixed windows of `window_s` seconds (numbered from the Unix epoch): a counter per owner, quota and window in
Redis (queue.owner_quota_key), so every API process shares it. `take` counts `n` more against the quota in
one script (read, compare, add: two requests of one key cannot both pass the last unit), or counts nothing
and raises KeyQuotaError with the seconds until the window ends (the API answers 429 quota_exceeded with that
Retry-After). `give_back` returns what a request took and did not use (its upload was a duplicate or failed).
A limit of 0 is no limit. The message names the quota and its limit, never the key or a session.
"""

from __future__ import annotations

import contextlib
import math
import time

import redis

from services.jobs import queue

# KEYS[1] the window's counter; ARGV n, limit, ttl. Returns the new count, or -1 (nothing counted) when over.
_TAKE = """
local used = tonumber(redis.call('GET', KEYS[1]) or '0')
if used + tonumber(ARGV[1]) > tonumber(ARGV[2]) then return -1 end
local now = redis.call('INCRBY', KEYS[1], ARGV[1])
redis.call('EXPIRE', KEYS[1], ARGV[3])
return now
"""
# KEYS[1] the window's counter; ARGV n. Only an existing counter is lowered (never below 0, never made anew).
_GIVE_BACK = """
local used = tonumber(redis.call('GET', KEYS[1]) or '0')
if used <= 0 then return 0 end
return redis.call('DECRBY', KEYS[1], math.min(used, tonumber(ARGV[1])))
"""


class KeyQuotaError(RuntimeError):
    """The key used its quota of sessions or frames for this window: nothing was counted (429 quota_exceeded)."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


def take(
    r: redis.Redis,
    prefix: str,
    owner: str,
    what: str,
    limit: int,
    window_s: int,
    n: int = 1,
    now: float | None = None,
) -> str | None:
    """Return the counter `n` more of `what` were counted on against the owner's quota (None: no limit, nothing
    counted); KeyQuotaError (nothing counted) when that would pass `limit` in the current window."""
    if limit <= 0 or not owner:
        return None
    now = time.time() if now is None else now
    window = int(now // window_s)
    key = queue.owner_quota_key(owner, what, window, prefix)
    if int(r.eval(_TAKE, 1, key, str(int(n)), str(int(limit)), str(2 * int(window_s)))) < 0:
        left = max(1, math.ceil((window + 1) * window_s - now))
        message = f"this key has used its quota of {limit} {what} per {window_s} s; retry after {left} s"
        raise KeyQuotaError(message, left)
    return key


def give_back(r: redis.Redis, counter: str | None, n: int = 1) -> None:
    """Return `n` units a request took (`take`'s counter) and did not use: its upload was a duplicate or failed.

    Best effort: it runs while another error is on its way out, which a Redis failure here must not replace; a
    unit not given back only counts against its key until the window ends."""
    if counter is not None:
        with contextlib.suppress(redis.RedisError):
            r.eval(_GIVE_BACK, 1, counter, str(int(n)))
