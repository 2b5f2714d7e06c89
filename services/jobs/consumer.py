"""A worker's side of the job streams, as a consumer of the group "workers": read new entries, take over
abandoned ones, keep a long job's entry claimed, and acknowledge. Reading with XREADGROUP and claiming change
the group's pending list, so they are Redis writes and live here (tests/services/jobs/test_one_writer.py)."""

from __future__ import annotations

from typing import Any

import redis

from services.jobs.queue import GROUP

Entry = tuple[str, str, dict[str, str]]  # (stream, entry id, fields)


def _text(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _fields(fields: dict[Any, Any] | None) -> dict[str, str]:
    return {_text(k): _text(v) for k, v in (fields or {}).items()}


def read_new(r: redis.Redis, consumer: str, streams: list[str], block_ms: int, count: int = 1) -> list[Entry]:
    """Return up to `count` entries never delivered before from `streams`, now pending to `consumer` (XREADGROUP),
    waiting at most block_ms for one."""
    resp = r.xreadgroup(GROUP, consumer, dict.fromkeys(streams, ">"), count=count, block=block_ms)
    return [(_text(stream), _text(eid), _fields(fields)) for stream, entries in resp or [] for eid, fields in entries]


def claim_idle(
    r: redis.Redis, stream: str, consumer: str, idle_ms: int, start: str = "0-0", count: int = 10
) -> tuple[str, list[tuple[str, dict[str, str] | None]]]:
    """Return (the next start id, "0-0" at the end; the entries taken over) after moving to `consumer` the entries
    of `stream` pending longer than idle_ms (XAUTOCLAIM); an entry deleted while pending comes with None fields.

    Redis 6.2 (the embedded server) answers such an entry as nil, without its id, and keeps it pending: its id is
    then found among the consumer's pending entries that are gone from the stream (Redis 7 drops them itself).
    """
    res = r.xautoclaim(stream, GROUP, consumer, idle_ms, start_id=start, count=count)
    claimed = [(_text(eid), _fields(fields) if fields else None) for eid, fields in res[1] if eid is not None]
    if any(eid is None for eid, _ in res[1]):
        claimed += [(eid, None) for eid in _gone_but_pending(r, stream, consumer) if eid not in dict(claimed)]
    return _text(res[0]), claimed


def _gone_but_pending(r: redis.Redis, stream: str, consumer: str) -> list[str]:
    """Return the ids pending to `consumer` whose entries are no longer in the stream (at most 100)."""
    pending = r.xpending_range(stream, GROUP, min="-", max="+", count=100, consumername=consumer)
    ids = [_text(p["message_id"]) for p in pending]
    return [eid for eid in ids if not r.xrange(stream, min=eid, max=eid, count=1)]


def ack(r: redis.Redis, stream: str, entry_id: str) -> None:
    """Acknowledge an entry that is already gone from the stream (deleted while pending): nothing to delete."""
    r.xack(stream, GROUP, entry_id)


def keep_claimed(r: redis.Redis, stream: str, consumer: str, entry_id: str) -> None:
    """Reset the idle time of an entry `consumer` is working on (XCLAIM to itself), so no other worker takes it."""
    r.xclaim(stream, GROUP, consumer, 0, [entry_id], justid=True)


def times_delivered(r: redis.Redis, stream: str, entry_id: str, consumer: str | None = None) -> int | None:
    """Return how many times a pending entry was delivered (XPENDING), or None when it is not pending (to
    `consumer`, when given)."""
    kwargs: dict[str, Any] = {"consumername": consumer} if consumer else {}
    pend = r.xpending_range(stream, GROUP, min=entry_id, max=entry_id, count=1, **kwargs)
    return int(pend[0]["times_delivered"]) if pend else None
