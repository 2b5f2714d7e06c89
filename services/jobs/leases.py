"""The registration lease of (session, version): one holder at a time, fencing tokens, no lost wake-ups.

acquire: SET lease "<consumer>:<token>" NX PX ttl with token = INCR fence (a holder re-acquiring keeps its
token). When another worker holds it, acquire sets the kick flag instead, and the holder's release refuses
(and clears the flag) while the flag is set, so work that arrived during the holder's last pass is never
left behind. A watchdog kick in the delayed ZSET (pushed forward on every renewal, removed on release)
wakes some worker after the holder dies, so a session is taken over even when nothing else arrives.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import redis

from services.jobs import delayed, queue

_ACQUIRE = """
local cur = redis.call('GET', KEYS[1])
if not cur then
  local token = redis.call('INCR', KEYS[2])
  redis.call('SET', KEYS[1], ARGV[1] .. ':' .. token, 'PX', ARGV[2])
  redis.call('DEL', KEYS[3])
  redis.call('ZADD', KEYS[4], ARGV[5], ARGV[4])
  return token
end
local prefix = ARGV[1] .. ':'
if string.sub(cur, 1, string.len(prefix)) == prefix then
  redis.call('PEXPIRE', KEYS[1], ARGV[2])
  return tonumber(string.sub(cur, string.len(prefix) + 1))
end
redis.call('SET', KEYS[3], '1', 'PX', ARGV[3])
return -1
"""

_RENEW = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  redis.call('PEXPIRE', KEYS[1], ARGV[2])
  if ARGV[4] ~= '' then redis.call('ZADD', KEYS[2], ARGV[3], ARGV[4]) end
  return 1
end
return 0
"""

_RELEASE = """
if redis.call('GET', KEYS[1]) ~= ARGV[1] then return -1 end
if ARGV[2] == 'normal' and redis.call('EXISTS', KEYS[3]) == 1 then
  redis.call('DEL', KEYS[3])
  return 0
end
redis.call('DEL', KEYS[1])
if ARGV[2] == 'handoff' then
  redis.call('ZADD', KEYS[2], ARGV[4], ARGV[3])
else
  redis.call('ZREM', KEYS[2], ARGV[3])
end
if ARGV[2] == 'final' then redis.call('DEL', KEYS[3]) end
return 1
"""

RELEASE_MODES = ("normal", "handoff", "final")


def watchdog_member(session_id: str, version: int, prefix: str) -> str:
    """Return the delayed-ZSET member of a session's registration kick (see services.jobs.delayed)."""
    return delayed.member(queue.register_stream(prefix), kick_fields(session_id, version))


def kick_fields(session_id: str, version: int) -> dict[str, str]:
    """Return the fields of a registration kick entry."""
    return {"kind": "register", "session": session_id, "version": str(int(version))}


@dataclass
class Lease:
    """A held lease: its Redis value and fencing token."""

    session_id: str
    version: int
    consumer: str
    token: int
    prefix: str

    @property
    def value(self) -> str:
        """Return the lease's value in Redis."""
        return f"{self.consumer}:{self.token}"

    def keys(self) -> list[str]:
        """Return [lease, delayed ZSET, kick flag] keys."""
        return [
            queue.lease_key(self.session_id, self.version, self.prefix),
            queue.delayed_key(self.prefix),
            queue.kick_key(self.session_id, self.version, self.prefix),
        ]

    def renew(self, r: redis.Redis, ttl_ms: int, watchdog_due: float | None) -> bool:
        """Return True when the lease was extended (watchdog kick pushed to watchdog_due, Unix s), False if not ours."""
        keys = self.keys()[:2]
        member = watchdog_member(self.session_id, self.version, self.prefix) if watchdog_due is not None else ""
        due = repr(float(watchdog_due)) if watchdog_due is not None else "0"
        return bool(r.eval(_RENEW, 2, *keys, self.value, int(ttl_ms), due, member))

    def release(self, r: redis.Redis, mode: str = "normal", handoff_delay_s: float = 0.0) -> int:
        """Return how releasing the lease went: 1 released, 0 refused (work arrived; flag cleared), -1 not ours.

        normal: refuse while the kick flag is set (the caller runs another pass), else release and drop the
        watchdog. handoff: release even so, and schedule the session's kick after handoff_delay_s so some
        worker continues (graceful stop, failures). final: release for good (session done or gone).
        """
        if mode not in RELEASE_MODES:
            raise ValueError(f"mode must be one of {RELEASE_MODES}")
        member = watchdog_member(self.session_id, self.version, self.prefix)
        due = repr(time.time() + handoff_delay_s)
        return int(r.eval(_RELEASE, 3, *self.keys(), self.value, mode, member, due))

    def held(self, r: redis.Redis) -> bool:
        """Return True if Redis still holds our value."""
        cur = r.get(self.keys()[0])
        return cur is not None and (cur.decode() if isinstance(cur, bytes) else cur) == self.value


def acquire(
    r: redis.Redis,
    session_id: str,
    version: int,
    consumer: str,
    ttl_ms: int,
    prefix: str,
    kick_ttl_ms: int = 60_000,
) -> Lease | None:
    """Return the lease taken (or ours kept, same token); None when another consumer holds it (kick flag set then).

    Taking it also sets the watchdog kick at now + 2 ttl (pushed forward by every renewal).
    """
    keys = [
        queue.lease_key(session_id, version, prefix),
        queue.fence_key(session_id, version, prefix),
        queue.kick_key(session_id, version, prefix),
        queue.delayed_key(prefix),
    ]
    due = repr(time.time() + 2.0 * ttl_ms / 1000.0)
    member = watchdog_member(session_id, version, prefix)
    token = int(r.eval(_ACQUIRE, 4, *keys, consumer, int(ttl_ms), int(kick_ttl_ms), member, due))
    if token < 0:
        return None
    return Lease(session_id, int(version), consumer, token, prefix)
