"""The job ledger (services/store/job_ledger.py): an accepted job's record before its 202, moved to finished once
done or failed, the open records the reconciler re-enqueues, and the run lock that lets one entry of a job run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.store.job_ledger import JobLedger
from services.store.storage import SessionStore


@pytest.fixture
def ledger(tmp_path: Path) -> JobLedger:
    """Return a ledger under tmp_path/jobs."""
    return JobLedger(tmp_path / "jobs")


def test_a_record_stays_open_until_its_job_finishes(ledger: JobLedger) -> None:
    first, second = "a" * 32, "b" * 32
    ledger.record(second, {"session": "s2", "created": "2026-01-02T00:00:00Z"})
    ledger.record(first, {"session": "s1", "created": "2026-01-01T00:00:00Z"})
    assert [d["id"] for d in ledger.open_jobs()] == [first, second]  # oldest first
    assert not ledger.is_finished(first)
    ledger.finish(first, "done")
    assert ledger.is_finished(first) and [d["id"] for d in ledger.open_jobs()] == [second]
    done = json.loads((ledger.root / "finished" / f"{first}.json").read_text())
    assert done == {"id": first, "session": "s1", "created": "2026-01-01T00:00:00Z", "state": "done"}
    ledger.record(first, {"session": "s1"})  # a late re-record of a finished job is a no-op
    assert [d["id"] for d in ledger.open_jobs()] == [second]
    ledger.discard(second)  # never accepted: no 202 was sent
    assert ledger.open_jobs() == [] and not ledger.is_finished(second)


def test_ids_that_are_not_32_hex_digits_are_refused(ledger: JobLedger) -> None:
    for bad in ("job-1", "../" + "a" * 29, "A" * 32):
        with pytest.raises(ValueError):
            ledger.record(bad, {})
        assert not ledger.is_finished(bad)


def test_the_session_store_keeps_its_ledger_under_data_dir_jobs(tmp_path: Path) -> None:
    store = SessionStore(tmp_path / "data")
    assert isinstance(store.jobs, JobLedger) and store.jobs.root == tmp_path / "data" / "jobs"


def test_job_run_lock_is_held_by_one_and_refuses_foreign_ids(ledger: JobLedger) -> None:
    job = "a" * 32
    with ledger.run_lock(job) as first, ledger.run_lock(job) as second:  # the second: another worker
        assert first and not second
    with ledger.run_lock(job) as again:
        assert again  # released when its holder is done
    with pytest.raises(ValueError):
        ledger.run_lock("job-1")  # at once, not when entered
    ledger.drop_run_lock(job)
    assert not (ledger.root / "running" / f"{job}.lock").exists()
