"""services.jobs.consumer: a worker's reads of the job streams (new entries, claims of idle ones, ack, keep claimed)
and services.jobs.reconcile_turn: the reconciler's lock and the key spacing its periodic runs."""

from __future__ import annotations

import time

from services.jobs import consumer, queue, reconcile_turn
from tests.workers.conftest import Backend


def _streams(backend: Backend) -> list[str]:
    queue.ensure_groups(backend.r, backend.prefix)
    return list(queue.worker_streams(backend.prefix))


def test_new_entries_are_read_once_decoded_and_stay_pending_to_their_reader(backend: Backend) -> None:
    r, streams = backend.r, _streams(backend)
    entry_id = r.xadd(streams[0], {"kind": "frame", "session": "s", "seq": "3"}).decode()
    got = consumer.read_new(r, "a", streams, block_ms=10)
    assert got == [(streams[0], entry_id, {"kind": "frame", "session": "s", "seq": "3"})]
    assert consumer.read_new(r, "b", streams, block_ms=10) == []  # delivered once to the group
    assert consumer.times_delivered(r, streams[0], entry_id, "a") == 1
    assert consumer.times_delivered(r, streams[0], entry_id, "b") is None  # not pending to b


def test_idle_entries_are_taken_over_and_a_deleted_one_is_acked(backend: Backend) -> None:
    r, streams = backend.r, _streams(backend)
    kept = r.xadd(streams[2], {"kind": "reprocess", "job": "j1"}).decode()
    gone = r.xadd(streams[2], {"kind": "reprocess", "job": "j2"}).decode()
    idle = r.xadd(streams[2], {"kind": "reprocess", "job": "j3"}).decode()
    assert len(consumer.read_new(r, "a", streams, block_ms=10, count=3)) == 3
    r.xdel(streams[2], gone)  # deleted while pending
    time.sleep(1.1)
    consumer.keep_claimed(r, streams[2], "a", kept)  # a long job's heartbeat: no longer idle
    start, claimed = consumer.claim_idle(r, streams[2], "b", idle_ms=1000)
    # Redis 6.2 (embedded) hands the deleted entry over with no fields; Redis 7 drops it from the pending list
    # itself (XAUTOCLAIM's deleted ids), so it is not handed over at all: either way it is not a job to run
    taken = dict(claimed)
    assert start == "0-0" and taken.pop(gone, None) is None and taken == {idle: {"kind": "reprocess", "job": "j3"}}
    assert consumer.times_delivered(r, streams[2], idle, "b") == 2
    assert consumer.times_delivered(r, streams[2], kept, "a") == 1  # still a's: the heartbeat kept it
    consumer.ack(r, streams[2], gone)
    assert consumer.times_delivered(r, streams[2], gone) is None


def test_one_reconciler_at_a_time_and_periodic_runs_spaced(backend: Backend) -> None:
    r, p = backend.r, backend.prefix
    assert reconcile_turn.acquire_lock(r, p, "a") and not reconcile_turn.acquire_lock(r, p, "b")
    reconcile_turn.release_lock(r, p, "b")  # not b's: stays a's
    assert not reconcile_turn.acquire_lock(r, p, "b")
    reconcile_turn.release_lock(r, p, "a")
    assert reconcile_turn.acquire_lock(r, p, "b")
    assert reconcile_turn.claim_periodic_run(r, p, "a", period_ms=300)
    assert not reconcile_turn.claim_periodic_run(r, p, "b", period_ms=300)  # a ran within the period
    time.sleep(0.4)
    assert reconcile_turn.claim_periodic_run(r, p, "b", period_ms=300)
    time.sleep(0.4)
    reconcile_turn.mark_run(r, p, "a", period_ms=300)  # an urgent run counts as the latest
    assert not reconcile_turn.claim_periodic_run(r, p, "b", period_ms=300)
