"""Fair job queueing (services.jobs.job_lanes): one lane per key, admitted onto the jobs stream round-robin."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import redis

from services.jobs import job_lanes, queue
from services.jobs import job_records as jobs
from services.store.job_ledger import JobLedger
from tests.services.jobs.test_queue import rq

__all__ = ["rq"]

A, B, C = "a" * 64, "b" * 64, "c" * 64


def _stream_jobs(r: redis.Redis, prefix: str) -> list[str]:
    return [fields[b"job"].decode() for _id, fields in r.xrange(queue.jobs_stream(prefix))]


def _serve_one(r: redis.Redis, prefix: str) -> str:
    """Take the oldest entry off the stream as a worker that finished it would (read, ack, delete)."""
    ((entry_id, fields),) = r.xrange(queue.jobs_stream(prefix), count=1)
    queue.ack_delete(r, queue.jobs_stream(prefix), entry_id)
    return fields[b"job"].decode()


def test_lanes_are_admitted_round_robin_up_to_in_flight(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    queue.ensure_groups(r, prefix)
    a = jobs.enqueue_jobs(r, prefix, A, [f"{i:032x}" for i in range(10)], {}, in_flight=3)
    assert _stream_jobs(r, prefix) == a[:3]  # the stream holds in_flight; the rest wait in A's lane
    b = jobs.enqueue_jobs(r, prefix, B, ["b" * 32] * 2, {}, in_flight=3)
    c = jobs.enqueue_jobs(r, prefix, C, ["c" * 32], {}, in_flight=3)
    assert _stream_jobs(r, prefix) == a[:3] and job_lanes.depth(r, prefix) == 13
    assert job_lanes.known_jobs(r, prefix) == {*a, *b, *c}  # the reconciler sees the waiting jobs
    served = []
    while len(served) < 13:
        served.append(_serve_one(r, prefix))
        job_lanes.admit(r, prefix, 3)
        assert r.xlen(queue.jobs_stream(prefix)) <= 3
    # after the three A had on the stream: one job per key in turn while a key has jobs waiting
    assert served == [*a[:3], a[3], b[0], c[0], a[4], b[1], *a[5:]]
    assert job_lanes.depth(r, prefix) == 0 and job_lanes.waiting(r, prefix) == {}
    assert r.llen(queue.job_lanes_key(prefix)) == 0  # the ring is empty once every lane is


def test_a_job_without_a_key_has_its_own_lane_and_a_gone_job_is_skipped(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    queue.ensure_groups(r, prefix)
    first, gone, kept = jobs.enqueue_jobs(r, prefix, "", ["1" * 32, "2" * 32, "3" * 32], {"k": 1}, in_flight=1)
    assert _stream_jobs(r, prefix) == [first]
    r.delete(queue.job_key(gone, prefix))  # expired or withdrawn while it waited
    _serve_one(r, prefix)
    assert job_lanes.admit(r, prefix, 1) == [kept]
    ((_id, fields),) = r.xrange(queue.jobs_stream(prefix))
    assert {k.decode(): v.decode() for k, v in fields.items()} == queue.job_entry(kept, "3" * 32, '{"k":1}')


def test_the_depth_limit_counts_waiting_jobs(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    jobs.enqueue_jobs(r, prefix, A, ["1" * 32] * 4, {}, in_flight=1, max_depth=5)
    assert r.xlen(queue.jobs_stream(prefix)) == 1 and job_lanes.depth(r, prefix) == 4
    with pytest.raises(jobs.QueueFullError):
        jobs.enqueue_jobs(r, prefix, B, ["2" * 32] * 2, {}, in_flight=1, max_depth=5)
    assert jobs.enqueue_jobs(r, prefix, B, ["2" * 32], {}, in_flight=1, max_depth=5)


def test_a_job_whose_ledger_record_failed_is_withdrawn_from_lane_and_stream(
    rq: tuple[redis.Redis, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    r, prefix = rq
    ledger = JobLedger(tmp_path / "jobs")
    kept = jobs.enqueue_jobs(r, prefix, A, ["1" * 32], {}, in_flight=2)

    def full_disk(job_id: str, fields: dict[str, str]) -> None:
        job_lanes.admit(r, prefix, 2)  # a worker admitted the new jobs meanwhile
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ledger, "record", full_disk)
    with pytest.raises(OSError):
        jobs.enqueue_jobs(r, prefix, A, ["2" * 32] * 3, {}, ledger=ledger, in_flight=2)
    assert _stream_jobs(r, prefix) == kept and job_lanes.waiting(r, prefix) == {}
    assert job_lanes.known_jobs(r, prefix) == set(kept)


def test_concurrent_admits_never_overfill_the_stream_nor_admit_twice(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    ids = [*jobs.enqueue_jobs(r, prefix, A, ["1" * 32] * 40, {}, in_flight=1),
           *jobs.enqueue_jobs(r, prefix, B, ["2" * 32] * 40, {}, in_flight=1)]  # fmt: skip
    with ThreadPoolExecutor(8) as pool:  # eight workers admitting at once
        admitted = [job for got in pool.map(lambda _: job_lanes.admit(r, prefix, 30), range(8)) for job in got]
    assert r.xlen(queue.jobs_stream(prefix)) == 30 and len(admitted) == 29 == len(set(admitted))
    assert set(_stream_jobs(r, prefix)) | {j for v in job_lanes.waiting(r, prefix).values() for j in v} == set(ids)
