"""The worker loop over the job streams (prepare frames, register sessions, reprocess and send jobs).

Reads <prefix>frames, <prefix>register and (when it holds no session) <prefix>jobs with XREADGROUP (group
"workers", consumer host:pid; services.jobs.consumer), after admitting the keys' waiting jobs onto <prefix>jobs
round-robin (services.jobs.job_lanes); acknowledges and deletes an entry once its results are
stored. Every loop it moves due delayed jobs back onto their streams and serves the sessions whose registration
lease it holds; every claim_every_s it XAUTOCLAIMs entries idle longer than claim_idle_ms (a crashed worker's).
An entry that failed max_deliveries times (delivery count from XPENDING plus the "attempt" field carried across
re-schedules) goes to <prefix>dead (workers.jobs.dead_letter). Which stage runs an entry: workers.jobs.dispatch;
a reprocess or send job's run and record: workers.jobs.runner.

Infrastructure faults (workers.faults: a full or failing disk, Redis unreachable or loading) never end the
process and never count against a job: the job is re-scheduled unchanged, and the loop backs off (bounded
exponential) until a step succeeds again. An entry whose re-scheduling failed because Redis was down stays
pending under this consumer and is retried by this worker as soon as Redis answers. The reconciler
(workers.reconciler) runs at start-up, after a Redis restart and periodically.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from pathlib import Path

import redis

from services.jobs import consumer, delayed, job_lanes, queue, worker_load
from workers.config import Context
from workers.faults import Backoff, describe, failure_frames, failure_reason, is_transient
from workers.jobs.dead_letter import dead_letter
from workers.jobs.dispatch import Dispatcher
from workers.jobs.runner import JobRunner
from workers.reconciler import Reconciler
from workers.retry import Retry
from workers.stages.register import RegisterStage
from workers.stages.reprocess import JobInterruptedError

log = logging.getLogger("veinmosaic.worker")


class Worker:
    """One worker's loop: read and claim entries, hand each to the dispatcher, then ack, re-schedule or dead-letter."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx
        self.register = RegisterStage(ctx)
        self.runner = JobRunner(ctx, self.beat)
        self.dispatcher = Dispatcher(ctx, self.register, self.runner)
        self.frames, self.kicks, self.jobs = queue.worker_streams(ctx.prefix)
        self._last_claim = 0.0
        self.backoff = Backoff(ctx.config.fault_backoff_first_s, ctx.config.fault_backoff_max_s)
        self.reconciler = Reconciler(ctx)
        self.faulted = False  # a transient fault was met during the current step
        self.stranded: dict[tuple[str, str], dict[str, str]] = {}  # pending entries to retry once Redis answers
        self._last_beat = 0.0
        self._published_held, self._published_at = -1, 0.0  # the session count last published (worker_load)

    # ----- the loop --------------------------------------------------------------------------------------------
    def run(self, max_seconds: float | None = None) -> None:
        """Serve until the stop flag is set (or max_seconds pass)."""
        ctx = self.ctx
        queue.ensure_groups(ctx.r, ctx.prefix)
        deadline = None if max_seconds is None else time.monotonic() + max_seconds
        log.info("worker %s started", ctx.config.consumer)
        try:
            while not ctx.stop.is_set() and (deadline is None or time.monotonic() < deadline):
                self.faulted = self.register.faulted = False
                self.beat()
                try:
                    self.step()
                except redis.ResponseError as exc:
                    if "NOGROUP" in str(exc):  # Redis was wiped: streams and groups are gone
                        self.fault(exc, "redis lost the consumer groups; recreating them and reconciling")
                        self.reconciler.urgent = True
                        with contextlib.suppress(redis.RedisError, OSError):
                            queue.ensure_groups(ctx.r, ctx.prefix)
                        continue
                    self.fault(exc)
                except Exception as exc:  # a worker never dies of one job or one fault
                    self.fault(exc)
                if self.faulted or self.register.faulted:
                    ctx.stop.wait(self.backoff.next())
                else:
                    self.backoff.reset()
        finally:
            with contextlib.suppress(redis.RedisError, OSError):
                self.register.release_all()
            log.info("worker %s stopped", ctx.config.consumer)

    def fault(self, exc: BaseException, message: str | None = None) -> None:
        """Log a fault of the loop (transient: a warning, else with its traceback) and back off after the step."""
        self.faulted = True
        delay = self.backoff.peek()
        if is_transient(exc):
            log.warning(message or "infrastructure fault (%s); backing off %.1f s", describe(exc), delay)
        else:
            log.error("unexpected error in the worker loop (%s); continuing", describe(exc), exc_info=exc)

    def beat(self) -> None:
        """Touch the heartbeat file (at most every 2 s) so a health check sees the loop turning."""
        path = self.ctx.config.heartbeat_file
        if not path or time.monotonic() - self._last_beat < 2.0:
            return
        self._last_beat = time.monotonic()
        try:
            os.utime(path)
        except FileNotFoundError:
            with contextlib.suppress(OSError):
                Path(path).touch()
        except OSError:
            pass

    def step(self) -> None:
        """One iteration: delayed jobs, claims, held sessions, then one blocking read and its entries."""
        ctx, cfg = self.ctx, self.ctx.config
        self.retry_stranded()
        self.reconciler.maybe_run()
        delayed.move_due(ctx.r, ctx.prefix)
        if time.monotonic() - self._last_claim >= cfg.claim_every_s:
            self._last_claim = time.monotonic()
            self.autoclaim()
        self.publish_load()
        self.register.poll()
        self.publish_load()
        if ctx.stop.is_set():
            return
        streams = [self.frames, self.kicks] if self.register.held else [self.frames, self.kicks, self.jobs]
        if not self.register.held:  # the keys' waiting jobs onto the job stream, round-robin (fair queueing)
            job_lanes.admit(ctx.r, ctx.prefix, cfg.jobs_in_flight)
        block = cfg.held_block_ms if self.register.held else cfg.block_ms
        for stream, entry_id, fields in consumer.read_new(ctx.r, cfg.consumer, streams, block):
            self.handle(stream, entry_id, fields, delivered=1)

    def autoclaim(self) -> None:
        """Take over entries other consumers left pending longer than claim_idle_ms, and handle them."""
        ctx, cfg = self.ctx, self.ctx.config
        for stream in (self.frames, self.kicks, self.jobs):
            start = "0-0"
            for _ in range(10):  # at most 10 pages per round
                start, claimed = consumer.claim_idle(ctx.r, stream, cfg.consumer, cfg.claim_idle_ms, start)
                for eid, fields in claimed:
                    if fields is None:  # deleted from the stream while pending
                        consumer.ack(ctx.r, stream, eid)
                        continue
                    delivered = consumer.times_delivered(ctx.r, stream, eid) or 1
                    log.info("claimed an entry idle > %d ms (delivery %d)", cfg.claim_idle_ms, delivered)
                    self.handle(stream, eid, fields, delivered=delivered)
                if start == "0-0":
                    break

    def retry_stranded(self) -> None:
        """Handle again the entries whose handling a Redis outage interrupted (still pending to this consumer)."""
        for (stream, entry_id), fields in list(self.stranded.items()):
            pending = consumer.times_delivered(self.ctx.r, stream, entry_id, self.ctx.config.consumer)
            del self.stranded[(stream, entry_id)]
            if pending is not None:  # still ours: handle it as the same delivery (the outage is not the job's failure)
                self.handle(stream, entry_id, fields, delivered=1)

    # ----- an entry's life: handled, then acked, re-scheduled or dead-lettered -------------------------------------
    def handle(self, stream: str, entry_id: str, fields: dict[str, str], delivered: int) -> None:
        """Handle one entry; ack+delete it when done, re-schedule it, or dead-letter it after too many failures.

        A transient (infrastructure) fault re-schedules the entry unchanged after the current back-off; it is
        never counted as a failure of the job. When even that fails (Redis down), the entry stays pending to
        this consumer and is handled again as soon as Redis answers.
        """
        try:
            self._handle(stream, entry_id, fields, delivered)
        except Exception as exc:
            if is_transient(exc):
                self.stranded[(stream, entry_id)] = fields
            raise

    def _handle(self, stream: str, entry_id: str, fields: dict[str, str], delivered: int) -> None:
        ctx, cfg = self.ctx, self.ctx.config
        attempt = int(fields.get("attempt", "0") or 0)
        failures = attempt + max(0, delivered - 1)
        if failures >= cfg.max_deliveries:
            dead_letter(self.ctx, self.runner, stream, entry_id, fields, f"failed {failures} times")
            return
        try:
            outcome = self.dispatcher.dispatch(stream, entry_id, fields)
        except JobInterruptedError:
            self._requeue(stream, entry_id, fields, 0.0, attempt)
            return
        except Exception as exc:
            if is_transient(exc):
                self.faulted = True
                kind = fields.get("kind")
                log.warning("job of kind %s met an infrastructure fault (%s); re-scheduled", kind, describe(exc))
                self._requeue(stream, entry_id, fields, self.backoff.peek(), attempt)
                return
            reason = failure_reason(exc)
            log.error("job of kind %s failed: %s\n%s", fields.get("kind"), reason, failure_frames(exc))
            if failures + 1 >= cfg.max_deliveries:
                dead_letter(self.ctx, self.runner, stream, entry_id, fields, reason)
            else:
                self._requeue(stream, entry_id, fields, 0.5 * (failures + 1), failures + 1)
            return
        if isinstance(outcome, Retry):
            self._requeue(stream, entry_id, fields, outcome.delay_s, failures)
            return
        queue.ack_delete(ctx.r, stream, entry_id)

    def _requeue(self, stream: str, entry_id: str, fields: dict[str, str], delay_s: float, attempt: int) -> None:
        """Put a copy of the entry back after delay_s (atomically enough: schedule first, then ack)."""
        new = dict(fields)
        if attempt:
            new["attempt"] = str(attempt)
        else:
            new.pop("attempt", None)
        delayed.schedule(self.ctx.r, stream, new, delay_s, self.ctx.prefix)
        queue.ack_delete(self.ctx.r, stream, entry_id)

    def publish_load(self) -> None:
        """Publish how many sessions this worker holds (when it changes, else at most every second)."""
        held, now = len(self.register.held), time.monotonic()
        if held != self._published_held or now - self._published_at >= 1.0:
            worker_load.publish_held(self.ctx.r, self.ctx.prefix, self.ctx.config.consumer, held)
            self._published_held, self._published_at = held, now
