"""Registration leases (fencing, kick flag, watchdog) and the delayed-job ZSET, on a real Redis."""

from __future__ import annotations

import time

from services.jobs import delayed, queue
from services.jobs.leases import acquire, watchdog_member
from tests.services.jobs.conftest import Backend

SID = "a" * 32


def test_lease_exclusive_with_increasing_tokens(backend: Backend) -> None:
    r, p = backend.r, backend.prefix
    a = acquire(r, SID, 1, "host:1", 5000, p)
    assert a is not None and a.token == 1
    assert acquire(r, SID, 1, "host:12", 5000, p) is None  # held by another consumer (prefix-safe names)
    again = acquire(r, SID, 1, "host:1", 5000, p)
    assert again is not None and again.token == 1  # the holder keeps its token
    assert a.renew(r, 5000, time.time() + 10)
    assert a.release(r) == 0  # refused: a kick arrived while held (the failed acquire set the flag) ...
    assert a.held(r)
    assert a.release(r) == 1  # ... and the flag was cleared by the refusal
    assert not a.held(r) and not a.renew(r, 5000, None)
    b = acquire(r, SID, 1, "host:12", 5000, p)
    assert b is not None and b.token == 2  # fencing: a new holder gets a larger token
    assert a.release(r) == -1  # the old holder cannot release the new holder's lease
    assert b.release(r, mode="final") == 1


def test_lease_expiry_and_watchdog(backend: Backend) -> None:
    r, p = backend.r, backend.prefix
    member = watchdog_member(SID, 1, p)
    a = acquire(r, SID, 1, "w1", 200, p)
    assert a is not None
    due = r.zscore(queue.delayed_key(p), member)
    assert due is not None and due > time.time()  # acquiring arms the watchdog kick
    time.sleep(0.35)
    b = acquire(r, SID, 1, "w2", 5000, p)  # the holder died: its lease expired
    assert b is not None and b.token == a.token + 1
    assert b.release(r, mode="handoff", handoff_delay_s=0.0) == 1
    assert r.zscore(queue.delayed_key(p), member) <= time.time()  # handoff: a kick is due now
    assert delayed.move_due(r, p) == 1
    entries = r.xrange(queue.register_stream(p))
    assert [f for _, f in entries] == [{b"kind": b"register", b"session": SID.encode(), b"version": b"1"}]
    c = acquire(r, SID, 1, "w3", 5000, p)
    assert c is not None and c.release(r) == 1
    assert r.zscore(queue.delayed_key(p), member) is None  # a normal release disarms the watchdog


def test_delayed_jobs_move_when_due_and_coalesce(backend: Backend) -> None:
    r, p = backend.r, backend.prefix
    stream = queue.frames_stream(p)
    now = 1000.0
    delayed.schedule(r, stream, {"kind": "frame", "session": SID, "seq": "3"}, 5.0, p, now=now)
    delayed.schedule(r, stream, {"kind": "frame", "session": SID, "seq": "3"}, 1.0, p, now=now)  # same job
    delayed.schedule(r, stream, {"kind": "frame", "session": SID, "seq": "4"}, 2.0, p, now=now)
    assert delayed.pending(r, p) == 2
    assert delayed.move_due(r, p, now=now + 0.5) == 0
    assert delayed.move_due(r, p, now=now + 1.5) == 1  # the earlier due time of the coalesced job won
    assert delayed.move_due(r, p, now=now + 2.5) == 1
    assert delayed.pending(r, p) == 0
    fields = [f for _, f in r.xrange(stream)]
    assert [f[b"seq"] for f in fields] == [b"3", b"4"] and all(f[b"kind"] == b"frame" for f in fields)
    r.zadd(queue.delayed_key(p), {"not json": 0})  # garbage is dropped, never blocks the others
    assert delayed.move_due(r, p, now=now) == 1 and delayed.pending(r, p) == 0
