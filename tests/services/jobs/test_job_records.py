"""The one job record (services/jobs/job_records.py) for both kinds of job: reprocess and send."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.jobs import job_records as jobs
from services.jobs import queue
from services.store.job_ledger import JobLedger
from tests.services.jobs.test_queue import rq

__all__ = ["rq"]


def _entries(r, prefix: str) -> list[dict[str, str]]:  # type: ignore[no-untyped-def]
    return [{k.decode(): v.decode() for k, v in fields.items()} for _id, fields in r.xrange(queue.jobs_stream(prefix))]


@pytest.mark.parametrize("kind", ["reprocess", "send"])
def test_job_kind_is_in_hash_entry_ledger_and_view(rq, tmp_path: Path, kind: str) -> None:  # type: ignore[no-untyped-def]
    r, prefix = rq
    ledger = JobLedger(tmp_path / "jobs")
    (job,) = jobs.enqueue_jobs(r, prefix, "f" * 64, ["a" * 32], {"destination": "pacs"}, ledger=ledger, kind=kind)
    assert jobs.read_job(r, prefix, job)["kind"] == kind
    assert _entries(r, prefix) == [
        {
            "kind": kind,
            "job": job,
            "session": "a" * 32,
            "options": json.dumps({"destination": "pacs"}, separators=(",", ":")),
        }
    ]
    (record,) = ledger.open_jobs()
    assert record["kind"] == kind and record["id"] == job
    view = jobs.job_view(jobs.read_job(r, prefix, job), job)
    assert view["kind"] == kind and view["state"] == "queued" and view["attempts"] == 0


def test_requeue_from_the_ledger_keeps_the_kind(rq, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    r, prefix = rq
    ledger = JobLedger(tmp_path / "jobs")
    (job,) = jobs.enqueue_jobs(r, prefix, "", ["b" * 32], {"destination": "pacs"}, ledger=ledger, kind="send")
    r.delete(queue.jobs_stream(prefix), queue.job_key(job, prefix))  # Redis lost the job
    (record,) = ledger.open_jobs()
    jobs.requeue_job(r, prefix, record, ttl_s=60)
    assert [e["kind"] for e in _entries(r, prefix)] == ["send"]
    assert jobs.read_job(r, prefix, job)["kind"] == "send"


def test_update_job_writes_progress_and_outcome(rq) -> None:  # type: ignore[no-untyped-def]
    r, prefix = rq
    (job,) = jobs.enqueue_jobs(r, prefix, "", ["c" * 32], {})
    jobs.update_job(r, prefix, job, state="running", version=3, done=0, total=40)
    jobs.update_job(r, prefix, job, done=40, state="done")
    view = jobs.job_view(jobs.read_job(r, prefix, job), job)
    assert (view["state"], view["version"], view["done"], view["total"], view["progress"]) == ("done", 3, 40, 40, 1.0)
    assert jobs.read_job(r, prefix, "0" * 32) == {}  # no such job


def test_unknown_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="job kind"):
        queue.job_entry("j", "s", "{}", kind="delete-everything")


def test_an_owner_over_its_quota_queues_nothing_and_others_are_unaffected(rq, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    r, prefix = rq
    ledger = JobLedger(tmp_path / "jobs")
    mine, theirs = "a" * 64, "b" * 64
    ids = jobs.enqueue_jobs(r, prefix, mine, ["1" * 32, "2" * 32], {}, ledger=ledger, max_per_owner=3)
    before = r.xlen(queue.jobs_stream(prefix))
    with pytest.raises(jobs.OwnerQuotaError, match="quota"):
        jobs.enqueue_jobs(r, prefix, mine, ["3" * 32, "4" * 32], {}, ledger=ledger, max_per_owner=3)  # 2 + 2 > 3
    assert r.xlen(queue.jobs_stream(prefix)) == before and len(ledger.open_jobs()) == 2  # nothing queued
    (one,) = jobs.enqueue_jobs(r, prefix, mine, ["3" * 32], {}, max_per_owner=3)  # exactly at the quota
    assert jobs.open_jobs(r, prefix, mine) == 3
    assert jobs.enqueue_jobs(r, prefix, theirs, ["5" * 32] * 3, {}, max_per_owner=3)  # another key: its own quota
    with pytest.raises(jobs.OwnerQuotaError):
        jobs.enqueue_jobs(r, prefix, mine, ["4" * 32], {}, max_per_owner=3)
    jobs.update_job(r, prefix, ids[0], state="running")  # running still counts ...
    with pytest.raises(jobs.OwnerQuotaError):
        jobs.enqueue_jobs(r, prefix, mine, ["4" * 32], {}, max_per_owner=3)
    jobs.update_job(r, prefix, ids[0], state="done")  # ... finished (or failed, or expired) frees a place
    r.delete(queue.job_key(one, prefix))
    assert jobs.open_jobs(r, prefix, mine) == 1
    assert len(jobs.enqueue_jobs(r, prefix, mine, ["4" * 32, "6" * 32], {}, max_per_owner=3)) == 2
    assert r.scard(queue.owner_jobs_key(mine, prefix)) == 3  # the finished ones left the owner's set then
    jobs.enqueue_jobs(r, prefix, mine, ["7" * 32], {})  # no quota given (an auto-send): queued, and counted
    assert jobs.open_jobs(r, prefix, mine) == 4


def test_concurrent_requests_of_one_owner_cannot_both_pass_its_quota(rq) -> None:  # type: ignore[no-untyped-def]
    import threading

    r, prefix = rq
    owner, outcomes, start = "c" * 64, [], threading.Barrier(8)

    def attempt() -> None:
        start.wait()
        try:
            jobs.enqueue_jobs(r, prefix, owner, ["8" * 32], {}, max_per_owner=5)
            outcomes.append("queued")
        except jobs.OwnerQuotaError:
            outcomes.append("refused")

    threads = [threading.Thread(target=attempt) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(outcomes) == ["queued"] * 5 + ["refused"] * 3
    assert jobs.open_jobs(r, prefix, owner) == 5 == r.xlen(queue.jobs_stream(prefix))
