"""Delayed jobs: a ZSET <prefix>delayed of {"s": stream, "f": fields} members scored by their due time (Unix s).

Any worker's loop moves due members back onto their streams with one atomic Lua call (ZRANGEBYSCORE + ZREM
+ XADD), so a job is never both delayed and queued, and none is lost if a worker dies. Identical jobs share
one member (the JSON is canonical), so repeated re-scheduling of the same job coalesces.
"""

from __future__ import annotations

import json
import time

import redis

from services.jobs import queue

_MOVE_DUE = """
local due = redis.call('ZRANGEBYSCORE', KEYS[1], '-inf', ARGV[1], 'LIMIT', 0, tonumber(ARGV[2]))
for _, member in ipairs(due) do
  redis.call('ZREM', KEYS[1], member)
  local ok, job = pcall(cjson.decode, member)
  if ok and type(job) == 'table' and type(job['s']) == 'string' and type(job['f']) == 'table' then
    local args = {}
    for k, v in pairs(job['f']) do
      table.insert(args, k)
      table.insert(args, tostring(v))
    end
    if #args > 0 then redis.call('XADD', job['s'], '*', unpack(args)) end
  end
end
return #due
"""


def member(stream: str, fields: dict[str, str]) -> str:
    """Return the canonical ZSET member of a job for `stream` with `fields`."""
    return json.dumps({"s": stream, "f": {k: str(v) for k, v in fields.items()}}, sort_keys=True, separators=(",", ":"))


def schedule(
    r: redis.Redis, stream: str, fields: dict[str, str], delay_s: float, prefix: str, now: float | None = None
) -> None:
    """Put a job on `stream` after delay_s seconds (an identical pending job keeps the earlier due time)."""
    due = (time.time() if now is None else now) + max(0.0, delay_s)
    r.zadd(queue.delayed_key(prefix), {member(stream, fields): due}, lt=True)
    # ZADD LT only updates existing members to an earlier time; a new member is added as usual.


def move_due(r: redis.Redis, prefix: str, now: float | None = None, limit: int = 100) -> int:
    """Return how many delayed jobs that are due were moved onto their streams (by this call)."""
    now = time.time() if now is None else now
    return int(r.eval(_MOVE_DUE, 1, queue.delayed_key(prefix), repr(float(now)), int(limit)))


def pending(r: redis.Redis, prefix: str) -> int:
    """Return the number of delayed jobs."""
    return int(r.zcard(queue.delayed_key(prefix)))
