"""Jobs in Redis (spec §5): enqueue, read back, progress; the one owner of the job and batch records.

Two kinds of job share this record: "reprocess" (a new results version) and "send" (a session's DICOM objects
sent to a PACS). A job is a Redis hash <prefix>job:<id> {id, kind, state: queued|running|done|failed, done,
total, session, version, error, owner, created, options, batch, attempts}, written in one MULTI with the job's
id appended to its owner's lane; the lanes are admitted round-robin onto the stream <prefix>jobs as entries
{"kind", "job", "session", "options"} (services.jobs.job_lanes: fair queueing across keys), so a worker never
sees an entry without its hash; a job's progress and outcome are written by `update_job` only. A batch is a
hash <prefix>batch:<id> {jobs: json list, owner, created, sessions}. Both expire JOB_TTL_S after they were
created.

Per-key quota: every job is also a member of its owner's set <prefix>owner:<fingerprint>:jobs, written in the
same MULTI. With max_per_owner, enqueue_jobs first counts the owner's open jobs (queued or running): members
whose record is done, failed or gone are taken out of the set then (lazily, only when the set is at the
quota, so the workers never write it), and OwnerQuotaError refuses jobs that would take the owner beyond the
quota. The check and the write are one optimistic transaction (WATCH on the owner's set): two concurrent
requests of one key cannot both pass it.
"""

from __future__ import annotations

import contextlib
import json
import time
import uuid
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Protocol

import redis

from services.jobs import job_lanes, queue

JOB_TTL_S = queue.JOB_TTL_S


class Ledger(Protocol):
    """The durable record of accepted jobs (services.store.job_ledger.JobLedger)."""

    def record(self, job_id: str, fields: dict[str, str]) -> None:
        """Record an accepted job durably (its Redis hash fields at creation); a no-op once it finished."""
        ...

    def discard(self, job_id: str) -> None:
        """Forget an open record (its job was never accepted: the 202 was not sent)."""
        ...


def new_id() -> str:
    """Return a fresh job or batch id (32 hex digits)."""
    return uuid.uuid4().hex


# the progress fields of a job waiting on the queue: a new job's, and a lost job's written again (requeue_job)
_QUEUED_STATE: Mapping[str, str] = MappingProxyType(
    {"state": "queued", "done": "0", "total": "0", "version": "", "error": ""}
)


def _job_fields(job_id: str, sid: str, owner: str, encoded: str, now: float, batch: str, kind: str) -> dict[str, str]:
    return {
        "id": job_id,
        "kind": kind,
        **_QUEUED_STATE,
        "session": sid,
        "owner": owner,
        "created": repr(float(now)),
        "options": encoded,
        "batch": batch,
    }


def queue_full(r: redis.Redis, prefix: str, adding: int, max_depth: int) -> bool:
    """Return True when `adding` more jobs would take the jobs queued or running (on the job stream or waiting in
    the keys' lanes) beyond max_depth."""
    return job_lanes.depth(r, prefix) + adding > max_depth


class QueueFullError(RuntimeError):
    """The job stream holds max_depth entries already: nothing was queued (the API answers 503 queue_full)."""


class OwnerQuotaError(RuntimeError):
    """The key has max_per_owner open jobs already: nothing was queued (the API answers 429 quota_exceeded)."""


FINISHED_STATES = ("done", "failed")


def _finished_members(r: redis.Redis, prefix: str, members: list[str]) -> list[str]:
    """Return the members of an owner's job set whose job is finished (done, failed) or whose record is gone."""
    pipe = r.pipeline(transaction=False)
    for job_id in members:
        pipe.hget(queue.job_key(job_id, prefix), "state")
    states = pipe.execute()
    return [
        job_id
        for job_id, state in zip(members, states, strict=True)
        if state is None or (state.decode() if isinstance(state, bytes) else str(state)) in FINISHED_STATES
    ]


def open_jobs(r: redis.Redis, prefix: str, owner: str) -> int:
    """Return how many of an owner's jobs are open (queued or running): the count its quota is checked against."""
    members = sorted(
        m.decode() if isinstance(m, bytes) else str(m) for m in r.smembers(queue.owner_jobs_key(owner, prefix))
    )
    return len(members) - len(_finished_members(r, prefix, members))


def _write_jobs(
    pipe: Any,
    prefix: str,
    owner: str,
    sessions: list[str],
    options: dict[str, Any],
    batch: str,
    kind: str,
    ids: list[str],
    now: float,
    max_per_owner: int | None,
) -> None:
    """Write the jobs in one MULTI (the batch hash, each job's hash and expiry, the jobs appended to the owner's
    lane, the owner's set) after the owner's quota check on its WATCHed set (redis.WatchError: try again)."""
    owned = queue.owner_jobs_key(owner, prefix)
    finished: list[str] = []
    if owner and max_per_owner is not None:
        pipe.watch(owned)  # immediate mode until multi(): the reads below answer now
        members = sorted(m.decode() if isinstance(m, bytes) else str(m) for m in pipe.smembers(owned))
        if len(members) + len(ids) > max_per_owner:
            finished = _finished_members(pipe, prefix, members)
            if len(members) - len(finished) + len(ids) > max_per_owner:
                pipe.unwatch()
                raise OwnerQuotaError(f"this key has {max_per_owner} jobs queued or running (its quota); retry later")
    pipe.multi()
    if batch:
        pipe.hset(
            queue.batch_key(batch, prefix),
            mapping={"jobs": json.dumps(ids), "owner": owner, "created": repr(now), "sessions": json.dumps(sessions)},
        )
        pipe.expire(queue.batch_key(batch, prefix), JOB_TTL_S)
    encoded = json.dumps(options, separators=(",", ":"))
    for job_id, sid in zip(ids, sessions, strict=True):
        pipe.hset(queue.job_key(job_id, prefix), mapping=_job_fields(job_id, sid, owner, encoded, now, batch, kind))
        pipe.expire(queue.job_key(job_id, prefix), JOB_TTL_S)
    job_lanes.append(pipe, prefix, owner, ids)  # admitted onto the jobs stream round-robin across owners
    if owner:
        if finished:
            pipe.srem(owned, *finished)
        pipe.sadd(owned, *ids)
        pipe.expire(owned, JOB_TTL_S)
    pipe.execute()


def enqueue_jobs(
    r: redis.Redis,
    prefix: str,
    owner: str,
    sessions: list[str],
    options: dict[str, Any],
    batch: str = "",
    ledger: Ledger | None = None,
    kind: str = "reprocess",
    max_depth: int | None = None,
    max_per_owner: int | None = None,
    in_flight: int = job_lanes.DEFAULT_IN_FLIGHT,
) -> list[str]:
    """Return the ids of the jobs written: one job hash per session, appended to the owner's lane (one MULTI).

    Each job is then recorded durably in the ledger (the 202's promise: the reconciler re-enqueues a recorded job
    Redis lost), and the lanes are admitted onto the jobs stream up to `in_flight` entries (job_lanes.admit,
    round-robin over the owners: another key's flood does not hold these jobs up).

    With max_depth, QueueFullError (nothing queued) when the jobs would take the stream beyond it; with
    max_per_owner, OwnerQuotaError (nothing queued) when they would give `owner` more open jobs than that. If the
    durable record fails (a full disk), the jobs are taken off Redis again and the OSError is raised.
    """
    if max_depth is not None and queue_full(r, prefix, len(sessions), max_depth):
        raise QueueFullError("the job queue is full; retry later")
    now = time.time()
    ids = [new_id() for _ in sessions]
    with r.pipeline(transaction=True) as pipe:
        while True:
            try:
                _write_jobs(pipe, prefix, owner, sessions, options, batch, kind, ids, now, max_per_owner)
                break
            except redis.WatchError:  # another request of this owner changed its set meanwhile: count again
                continue
    encoded = json.dumps(options, separators=(",", ":"))
    records = {
        job_id: _job_fields(job_id, sid, owner, encoded, now, batch, kind)
        for job_id, sid in zip(ids, sessions, strict=True)
    }
    if ledger is not None:
        try:
            for job_id in ids:
                fields = records[job_id]
                keys = ("kind", "session", "owner", "created", "options", "batch")
                ledger.record(job_id, {k: fields[k] for k in keys})
        except OSError:
            with contextlib.suppress(redis.RedisError, OSError):
                job_lanes.withdraw(r, prefix, owner, ids)  # out of the lane (and the stream, if admitted meanwhile)
                undo = r.pipeline(transaction=True)
                undo.delete(*(queue.job_key(job_id, prefix) for job_id in ids))
                if owner:
                    undo.srem(queue.owner_jobs_key(owner, prefix), *ids)
                undo.execute()
            for job_id in ids:
                with contextlib.suppress(OSError):
                    ledger.discard(job_id)
            raise
    with contextlib.suppress(redis.RedisError, OSError):  # else a worker admits them before its next read
        job_lanes.admit(r, prefix, in_flight)
    return ids


def requeue_job(r: redis.Redis, prefix: str, fields: dict[str, str], ttl_s: int = JOB_TTL_S) -> None:
    """Write a job's record as queued again (from its creation fields, e.g. the ledger's) and its stream entry, in
    one MULTI: the reconciler's re-enqueue of a job Redis lost."""
    job_id = fields["id"]
    pipe = r.pipeline(transaction=True)
    pipe.hset(queue.job_key(job_id, prefix), mapping={**fields, **_QUEUED_STATE})
    pipe.expire(queue.job_key(job_id, prefix), ttl_s)
    kind = fields.get("kind") or "reprocess"
    pipe.xadd(
        queue.jobs_stream(prefix), queue.job_entry(job_id, fields.get("session", ""), fields.get("options", "{}"), kind)
    )
    if fields.get("owner"):  # it counts against its key's quota again
        pipe.sadd(queue.owner_jobs_key(fields["owner"], prefix), job_id)
        pipe.expire(queue.owner_jobs_key(fields["owner"], prefix), ttl_s)
    pipe.execute()


def _decode(raw: dict[Any, Any]) -> dict[str, str]:
    return {
        (k.decode() if isinstance(k, bytes) else k): (v.decode() if isinstance(v, bytes) else v) for k, v in raw.items()
    }


def read_job(r: redis.Redis, prefix: str, job_id: str) -> dict[str, str]:
    """Return a job's hash (decoded), {} when there is none."""
    return _decode(r.hgetall(queue.job_key(job_id, prefix)))


def update_job(r: redis.Redis, prefix: str, job_id: str, **values: object) -> None:
    """Set fields of a job's record (state, done, total, version, error, attempts, ...): the one writer of a job's
    progress and outcome once it is enqueued (the workers' reprocess and send stages, the dead-lettering loop)."""
    r.hset(queue.job_key(job_id, prefix), mapping={k: str(v) for k, v in values.items()})


def read_batch(r: redis.Redis, prefix: str, batch_id: str) -> tuple[dict[str, str], list[tuple[str, dict[str, str]]]]:
    """Return a batch's hash ({} when there is none) and (job id, job hash) of each of its jobs still stored."""
    raw = _decode(r.hgetall(queue.batch_key(batch_id, prefix)))
    if not raw:
        return {}, []
    ids = json.loads(raw.get("jobs") or "[]")
    pipe = r.pipeline(transaction=False)
    for job_id in ids:
        pipe.hgetall(queue.job_key(job_id, prefix))
    return raw, [(job_id, _decode(h)) for job_id, h in zip(ids, pipe.execute(), strict=True) if h]


def job_view(raw: dict[str, str], job_id: str) -> dict[str, Any]:
    """Return the public state of a job from its hash: id, kind, status (and state, its deprecated alias in the
    API), session, version, done, total, progress, error, created, batch, options, attempts (a damaged field reads
    as its empty value)."""

    def as_int(name: str) -> int:
        try:
            return int(float(raw.get(name) or 0))
        except ValueError:
            return 0

    done, total = as_int("done"), as_int("total")
    try:
        options = json.loads(raw.get("options") or "{}")
    except ValueError:
        options = {}
    created = raw.get("created")
    return {
        "id": job_id,
        "kind": raw.get("kind") or "reprocess",
        "status": raw.get("state") or "queued",
        "state": raw.get("state") or "queued",
        "session": raw.get("session", ""),
        "version": as_int("version") or None,
        "done": done,
        "total": total,
        "progress": (min(1.0, done / total) if total > 0 else (1.0 if raw.get("state") == "done" else None)),
        "error": raw.get("error") or None,
        "created": float(created) if created else None,
        "batch": raw.get("batch") or None,
        "options": options if isinstance(options, dict) else {},
        "attempts": as_int("attempts"),
    }


def batch_state(states: set[str]) -> str:
    """Return a batch's overall state from its jobs' states: done when all are done, failed when all ended and
    one failed, queued when none started, else running."""
    if states <= {"done"}:
        return "done"
    if states <= {"done", "failed"}:
        return "failed"
    if states <= {"queued"}:
        return "queued"
    return "running"
