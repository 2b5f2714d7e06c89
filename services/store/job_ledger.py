"""The job ledger: the durable record of accepted jobs (reprocess and send) under data_dir/jobs.

Layout:
    jobs/<id>.json            an accepted job's record (its creation fields), written before its 202
    jobs/finished/<id>.json   the record once the job is done or failed (with its state)
    jobs/running/<id>.lock    the run lock held by the worker running the job
Redis holds the work list; this holds the promise. The workers' reconciler re-enqueues an open record whose job
Redis lost (services.jobs.job_records.requeue_job).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path
from typing import Any

from services.store.durable import atomic_write_bytes, fsync_dir, try_lock


def _json_bytes(doc: Any) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=False, sort_keys=True).encode()


_JOB_ID = re.compile(r"^[0-9a-f]{32}$")


class JobLedger:
    """The durable record of accepted reprocess jobs: Redis holds the work list, this the promise (a 202).

    jobs/<id>.json is written (atomically, fsynced) before a job's 202 and moved to jobs/finished/<id>.json
    once the job is done or failed; the workers' reconciler re-enqueues an open record whose job Redis lost.
    A record holds the job's creation fields only (session, owner fingerprint, options, batch, created).
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def _path(self, job_id: str, finished: bool = False) -> Path:
        if not isinstance(job_id, str) or not _JOB_ID.match(job_id):
            raise ValueError("job ids are 32 hex digits")
        return (self.root / "finished" if finished else self.root) / f"{job_id}.json"

    def record(self, job_id: str, fields: dict[str, str]) -> None:
        """Record an accepted job durably (its Redis hash fields at creation); a no-op once it finished."""
        if self._path(job_id, finished=True).exists():
            return
        self.root.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self._path(job_id), _json_bytes({**fields, "id": job_id}))

    def discard(self, job_id: str) -> None:
        """Forget an open record (its job was never accepted: the 202 was not sent)."""
        with contextlib.suppress(FileNotFoundError):
            self._path(job_id).unlink()

    def finish(self, job_id: str, state: str) -> None:
        """Mark a job done or failed: its record moves to jobs/finished (written even without an open one)."""
        done_dir = self.root / "finished"
        done_dir.mkdir(parents=True, exist_ok=True)
        try:
            doc = json.loads(self._path(job_id).read_bytes())
        except FileNotFoundError:
            doc = {"id": job_id}
        atomic_write_bytes(self._path(job_id, finished=True), _json_bytes({**doc, "state": state}))
        self.discard(job_id)
        fsync_dir(self.root)

    def is_finished(self, job_id: str) -> bool:
        """Return True once the job was recorded done or failed."""
        try:
            return self._path(job_id, finished=True).exists()
        except ValueError:
            return False

    def run_lock(self, job_id: str) -> contextlib.AbstractContextManager[bool]:
        """Return job_id's run lock, held while the job runs: it yields True if taken, False while another worker
        runs the job. ValueError (at once) for an id that is not 32 hex digits.

        Two entries of one job can exist at once (Redis lost the running job's entry and the reconciler queued
        it again); the lock lets only one of them run. A dead holder's lock is released by the kernel.
        """
        path = self._lock_path(job_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        return try_lock(path)

    def drop_run_lock(self, job_id: str) -> None:
        """Remove a finished job's lock file (called by its holder: whoever opened the file meanwhile finds the
        job finished once it gets the lock, and a newcomer makes a new file and finds the same)."""
        with contextlib.suppress(FileNotFoundError, ValueError):
            self._lock_path(job_id).unlink()

    def _lock_path(self, job_id: str) -> Path:
        if not isinstance(job_id, str) or not _JOB_ID.match(job_id):
            raise ValueError("job ids are 32 hex digits")
        return self.root / "running" / f"{job_id}.lock"

    def open_jobs(self) -> list[dict[str, str]]:
        """Return the records of accepted jobs not yet finished (oldest first)."""
        out = []
        with contextlib.suppress(FileNotFoundError), os.scandir(self.root) as it:
            for e in it:
                if e.name.endswith(".json") and _JOB_ID.match(e.name[:-5]):
                    with contextlib.suppress(FileNotFoundError, ValueError):
                        out.append({str(k): str(v) for k, v in json.loads(Path(e.path).read_bytes()).items()})
        return sorted(out, key=lambda d: (d.get("created", ""), d.get("id", "")))
