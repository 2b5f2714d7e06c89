"""Fair job queueing across keys: one lane of waiting jobs per key, admitted onto the jobs stream round-robin.

A reprocess or send job is not put on the jobs stream (<prefix>jobs) when it is accepted: its id goes to the end
of its owner's lane (<prefix>lane:<owner>, a list; owner "" is the lane "-"), and the owner to the end of the
ring of owners with waiting jobs (<prefix>lanes, each owner at most once) if it is not there. `admit` then fills
the stream up to `in_flight` entries (XLEN: jobs waiting on the stream or running, since a finished entry is
deleted) by taking one job from the owner at the head of the ring, putting that owner back at the end while
its lane still holds jobs, and so on: one key's thousand queued jobs wait in its lane, and another key's job
goes on the stream after at most `in_flight` + 1 of them. The API admits after every enqueue, a worker before
it reads the jobs stream; `admit` is one Lua script, so concurrent admits never overfill the stream or take a
job twice. A job whose hash is gone (expired, withdrawn) is skipped. Jobs the stream already held (a re-scheduled
job coming back from the delayed set, the reconciler's re-enqueue of a job Redis lost) bypass the lanes.

The script names the lane and job keys it reads from their prefixes (queue.job_lane_key, queue.job_key), so it
needs a single Redis server (not a cluster), as the rest of the queue does.
"""

from __future__ import annotations

from collections.abc import Sequence

import redis

from services.jobs import queue

DEFAULT_IN_FLIGHT = 8  # Settings.queue_jobs_in_flight's default

# KEYS[1] a lane, KEYS[2] the ring; ARGV[1] the owner's ring member, ARGV[2..] job ids to append to the lane
_APPEND = """
redis.call('RPUSH', KEYS[1], unpack(ARGV, 2))
if not redis.call('LPOS', KEYS[2], ARGV[1]) then redis.call('RPUSH', KEYS[2], ARGV[1]) end
return redis.call('LLEN', KEYS[1])
"""
# KEYS[1] the jobs stream, KEYS[2] the ring; ARGV[1] in_flight, ARGV[2] the key prefix (a ring member is its lane's
# key without it), ARGV[3] the job hashes' key prefix.
# Returns the ids of the jobs put on the stream, in order.
_ADMIT = """
local depth = redis.call('XLEN', KEYS[1])
local window = tonumber(ARGV[1])
local admitted = {}
local turns = 0
while depth < window do
  local owner = redis.call('LPOP', KEYS[2])
  if not owner then break end
  local lane = ARGV[2] .. owner
  local job = redis.call('LPOP', lane)
  if job then
    local f = redis.call('HMGET', ARGV[3] .. job, 'kind', 'session', 'options')
    if f[1] then
      redis.call('XADD', KEYS[1], '*', 'kind', f[1], 'job', job, 'session', f[2] or '', 'options', f[3] or '{}')
      depth = depth + 1
      admitted[#admitted + 1] = job
    end
  end
  if redis.call('LLEN', lane) > 0 then redis.call('RPUSH', KEYS[2], owner) end
  turns = turns + 1
  if turns > 100000 then break end
end
return admitted
"""


def _member(owner: str) -> str:
    """Return the ring member of an owner: its lane's key without the prefix."""
    return queue.job_lane_key(owner, "")


def append(pipe: redis.Redis, prefix: str, owner: str, job_ids: Sequence[str]) -> None:
    """Append jobs (their hashes written in the same MULTI) to the end of their owner's lane (`pipe`: a pipeline)."""
    if job_ids:
        ring = queue.job_lanes_key(prefix)
        pipe.eval(_APPEND, 2, queue.job_lane_key(owner, prefix), ring, _member(owner), *job_ids)


def admit(r: redis.Redis, prefix: str, in_flight: int = DEFAULT_IN_FLIGHT) -> list[str]:
    """Return the ids of the jobs put on the jobs stream now, round-robin over the owners' lanes, until the stream
    holds `in_flight` entries (queued there or running) or the lanes are empty."""
    reply = r.eval(
        _ADMIT,
        2,
        queue.jobs_stream(prefix),
        queue.job_lanes_key(prefix),
        str(max(1, int(in_flight))),
        prefix,  # a ring member is its lane's key without the prefix
        queue.job_key("", prefix),
    )
    return [_text(j) for j in reply or []]


def waiting(r: redis.Redis, prefix: str) -> dict[str, list[str]]:
    """Return the job ids waiting in each lane that holds any (ring member -> ids, oldest first)."""
    members = [_text(m) for m in r.lrange(queue.job_lanes_key(prefix), 0, -1)]
    pipe = r.pipeline(transaction=False)
    for member in members:
        pipe.lrange(prefix + member, 0, -1)
    lanes = pipe.execute() if members else []
    return {m: [_text(j) for j in ids] for m, ids in zip(members, lanes, strict=True) if ids}


def depth(r: redis.Redis, prefix: str) -> int:
    """Return how many jobs are queued or running: the jobs stream's entries plus those waiting in lanes (counted
    with LLEN: every enqueue and every metrics scrape asks, and the ids themselves are not needed)."""
    members = [_text(m) for m in r.lrange(queue.job_lanes_key(prefix), 0, -1)]
    pipe = r.pipeline(transaction=False)
    pipe.xlen(queue.jobs_stream(prefix))
    for member in members:
        pipe.llen(prefix + member)
    return sum(int(n) for n in pipe.execute())


def known_jobs(r: redis.Redis, prefix: str) -> set[str]:
    """Return the ids of the jobs Redis holds: waiting in a lane, on the jobs stream (pending included) or delayed.

    The lanes are read first: a job admitted meanwhile is then seen twice rather than not at all."""
    in_lanes = {job for ids in waiting(r, prefix).values() for job in ids}
    return in_lanes | queue.known_jobs(r, prefix)


def withdraw(r: redis.Redis, prefix: str, owner: str, job_ids: Sequence[str]) -> None:
    """Take jobs that were never accepted (their 202 not sent) out of their owner's lane, and off the jobs stream
    if an admit moved them there meanwhile."""
    if not job_ids:
        return
    lane = queue.job_lane_key(owner, prefix)
    pipe = r.pipeline(transaction=True)
    for job in job_ids:
        pipe.lrem(lane, 0, job)
    pipe.execute()
    wanted, stream = set(job_ids), queue.jobs_stream(prefix)
    entries = [eid for eid, f in r.xrange(stream, "-", "+") if _text(f.get(b"job", f.get("job"))) in wanted]
    if entries:
        r.xdel(stream, *entries)


def _text(value: object) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)
