"""Running a reprocess or send job once (workers.stages.reprocess, workers.stages.send): under the job's run lock,
keeping its stream entry claimed while it runs, then closing its durable record in the job ledger."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable

import redis

from services.jobs import consumer
from services.jobs import job_records as jobs
from workers.config import Context
from workers.faults import describe
from workers.retry import Retry
from workers.stages.reprocess import handle_job
from workers.stages.send import handle_send

log = logging.getLogger("veinmosaic.worker")


class JobRunner:
    """Runs reprocess and send jobs, one run at a time per job across the workers, and closes their records."""

    def __init__(self, ctx: Context, beat: Callable[[], None]) -> None:
        self.ctx = ctx
        self.beat = beat  # the loop's heartbeat, touched while a long job runs

    def run(self, stream: str, entry_id: str, fields: dict[str, str]) -> Retry | None:
        """Return a Retry (the entry comes back after its delay) or None, running a job (reprocess or send) once.

        It runs under its run lock, unless it is finished (then the entry is dropped) or running in another worker
        (then the entry waits job_busy_retry_s and looks again). A send may answer Retry (session not done, PACS
        unreachable): its entry comes back after the delay.
        """
        ctx, job_id = self.ctx, fields.get("job", "")
        if self.settled(job_id):  # a second entry of a finished job (a reconciler race)
            log.info("entry of a finished job dropped")
            return None
        try:
            lock = ctx.store.jobs.run_lock(job_id)
        except ValueError:  # not an id the API makes (uuid4 hex): nothing to lock by, the job runs unlocked
            lock = contextlib.nullcontext(True)
        with lock as held:
            if not held:
                log.info("reprocess job already running in another worker; its second entry waits")
                return Retry(ctx.config.job_busy_retry_s, "running elsewhere")
            if self.settled(job_id):  # finished between the first look and taking the lock
                return None

            def heartbeat() -> None:  # keep the entry from looking abandoned while the job runs
                consumer.keep_claimed(ctx.r, stream, ctx.config.consumer, entry_id)
                self.beat()

            if fields.get("kind") == "send":
                outcome = handle_send(ctx, fields, heartbeat)
                if isinstance(outcome, Retry):
                    return outcome
            else:
                handle_job(ctx, fields, heartbeat)
            self.finish(job_id)
            ctx.store.jobs.drop_run_lock(job_id)
        return None

    def settled(self, job_id: str) -> bool:
        """Return True when the job is done or failed (its durable record, else its Redis hash says so)."""
        if self.ctx.store.jobs.is_finished(job_id):
            return True
        if jobs.read_job(self.ctx.r, self.ctx.prefix, job_id).get("state") in ("done", "failed"):
            self.finish(job_id)  # the record stayed open (a write failed after the job): close it now
            return True
        return False

    def finish(self, job_id: str, state: str | None = None) -> None:
        """Close a reprocess job's durable record (done or failed); if the disk refuses, the reconciler does it.

        Never raised: the job itself is finished, and re-running it for a failed bookkeeping write would be
        worse than a record that stays open until the reconciler reads the job's final state from Redis.
        """
        if not job_id:
            return
        try:
            if state is None:
                state = jobs.read_job(self.ctx.r, self.ctx.prefix, job_id).get("state") or "done"
            self.ctx.store.jobs.finish(job_id, state)
        except (OSError, ValueError, redis.RedisError) as exc:
            log.warning("reprocess job record not closed (%s); the reconciler will", describe(exc))
