"""How many registration sessions each live worker holds, so new sessions go to the least loaded worker.

One hash, <prefix>load, holds a field per worker: "<count>:<expiry ms>" by the Redis server's clock (no skew
between hosts). A worker refreshes its field every loop turn; a reader drops the fields that expired (a worker
dead, or busy in a long job, drops out) and reads the rest in the same round trip, so nothing scans the
keyspace. Registration of a session is serial in the worker holding its lease, so sessions piling up on one
worker would leave the others preparing frames for it (measured: 3 probes on 2 workers, all held by one: it at
100 % CPU, the other at 42 %).
"""

from __future__ import annotations

import redis

LOAD_TTL_MS = 5000  # a worker's count lives this long unless refreshed

_PUBLISH = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
redis.call('HSET', KEYS[1], ARGV[1], ARGV[2] .. ':' .. (now + tonumber(ARGV[3])))
return 1
"""

_FEWEST_ELSEWHERE = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
local all = redis.call('HGETALL', KEYS[1])
local fewest = -1
for i = 1, #all, 2 do
  local field, value = all[i], all[i + 1]
  local sep = string.find(value, ':', 1, true)
  local count, expiry = tonumber(string.sub(value, 1, sep - 1)), tonumber(string.sub(value, sep + 1))
  if expiry <= now then
    redis.call('HDEL', KEYS[1], field)
  elseif field ~= ARGV[1] and (fewest < 0 or count < fewest) then
    fewest = count
  end
end
return fewest
"""


def load_key(prefix: str) -> str:
    """Return the hash holding every worker's held-session count."""
    return f"{prefix}load"


def publish_held(r: redis.Redis, prefix: str, consumer: str, held: int) -> None:
    """Record that `consumer` holds `held` sessions (dropped after LOAD_TTL_MS unless published again)."""
    r.eval(_PUBLISH, 1, load_key(prefix), consumer, int(held), LOAD_TTL_MS)


def fewest_held_elsewhere(r: redis.Redis, prefix: str, consumer: str) -> int | None:
    """Return the smallest session count another live worker holds, or None when no other worker is live."""
    fewest = int(r.eval(_FEWEST_ELSEWHERE, 1, load_key(prefix), consumer))
    return fewest if fewest >= 0 else None
