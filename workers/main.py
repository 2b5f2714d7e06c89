"""The worker process: one loop over the job streams (prepare frames, register sessions, reprocess jobs).

Reads <prefix>frames, <prefix>register and (when it holds no session) <prefix>jobs with XREADGROUP (group
"workers", consumer host:pid); acknowledges and deletes an entry once its results are stored. Every loop it
moves due delayed jobs back onto their streams and serves the sessions whose registration lease it holds;
every claim_every_s it XAUTOCLAIMs entries idle longer than claim_idle_ms (a crashed worker's). An entry
that failed max_deliveries times (delivery count from XPENDING plus the "attempt" field carried across
re-schedules) goes to <prefix>dead; a dead frame is marked poison and registered as rejected. SIGTERM or
SIGINT stops the loop after the current entry; held sessions are flushed and handed off.

Infrastructure faults (workers.faults: a full or failing disk, Redis unreachable or loading) never end the
process and never count against a job: the job is re-scheduled unchanged, and the loop backs off (bounded
exponential) until a step succeeds again. An entry whose re-scheduling failed because Redis was down stays
pending under this consumer and is retried by this worker as soon as Redis answers. The reconciler
(workers.reconciler) runs at start-up, after a Redis restart and periodically.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import redis

from services.core.inputs.image_header import DEFAULT_MAX_FRAME_SIDE
from services.decoder_limits import set_decoder_limits
from services.jobs import consumer, dead_letters, delayed, queue, worker_load
from services.jobs import reprocess as jobs
from services.jobs.redis_backend import close, connect
from services.settings import Settings
from services.store.results_store import LIVE_VERSION, ResultsStore
from services.store.storage import SessionNotFoundError, SessionStore
from workers.config import Context, WorkerConfig
from workers.faults import Backoff, describe, failure_frames, failure_reason, is_transient
from workers.reconciler import Reconciler
from workers.stages.prepare import Retry, handle_frame
from workers.stages.register import RegisterStage
from workers.stages.reprocess import JobInterruptedError, handle_job
from workers.stages.send import handle_send

log = logging.getLogger("veinmosaic.worker")


# A kick declined by a worker busier than another (Worker.busier_than_another) comes back after this long, for
# the less loaded worker to take; short, so a new session waits a fraction of a second at most once or twice.
DECLINE_DELAY_S = 0.2


class Worker:
    """One worker's loop and dispatch."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx
        self.register = RegisterStage(ctx)
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

    # ----- dispatch --------------------------------------------------------------------------------------------
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
            self.dead_letter(stream, entry_id, fields, f"failed {failures} times")
            return
        try:
            outcome = self.dispatch(stream, entry_id, fields)
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
                self.dead_letter(stream, entry_id, fields, reason)
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

    def dispatch(self, stream: str, entry_id: str, fields: dict[str, str]) -> Retry | str | None:
        """Return the outcome of running the stage an entry belongs to: a Retry (back after its delay), DONE or None."""
        ctx = self.ctx
        kind = fields.get("kind")
        sid = fields.get("session", "")
        if kind == "frame":
            return handle_frame(ctx, sid, int(fields["seq"]))
        if kind in ("finish", "register"):
            version = LIVE_VERSION if kind == "finish" else int(fields.get("version", LIVE_VERSION))
            if self.busier_than_another(sid, version):
                return Retry(DECLINE_DELAY_S, "another worker holds fewer sessions")
            self.register.on_kick(sid, version)
            return None
        if kind in ("reprocess", "send"):
            return self.run_job(stream, entry_id, fields)
        log.warning("entry of unknown kind dropped")
        return None

    def busier_than_another(self, sid: str, version: int) -> bool:
        """Return True when this worker does not hold the session and another live worker holds fewer sessions:
        the kick waits DECLINE_DELAY_S for that worker, so sessions spread over the workers."""
        held = len(self.register.held)
        if not held or (sid, int(version)) in self.register.held:
            return False
        fewest = worker_load.fewest_held_elsewhere(self.ctx.r, self.ctx.prefix, self.ctx.config.consumer)
        return fewest is not None and fewest < held

    def publish_load(self) -> None:
        """Publish how many sessions this worker holds (when it changes, else at most every second)."""
        held, now = len(self.register.held), time.monotonic()
        if held != self._published_held or now - self._published_at >= 1.0:
            worker_load.publish_held(self.ctx.r, self.ctx.prefix, self.ctx.config.consumer, held)
            self._published_held, self._published_at = held, now

    def run_job(self, stream: str, entry_id: str, fields: dict[str, str]) -> Retry | None:
        """Return a Retry (the entry comes back after its delay) or None, running a job (reprocess or send) once.

        It runs under its run lock, unless it is finished (then the entry is dropped) or running in another worker
        (then the entry waits job_busy_retry_s and looks again). A send may answer Retry (session not done, PACS
        unreachable): its entry comes back after the delay.
        """
        ctx, job_id = self.ctx, fields.get("job", "")
        if self._job_settled(job_id):  # a second entry of a finished job (a reconciler race)
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
            if self._job_settled(job_id):  # finished between the first look and taking the lock
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
            self.finish_job(job_id)
            ctx.store.jobs.drop_run_lock(job_id)
        return None

    def _job_settled(self, job_id: str) -> bool:
        """Return True when the job is done or failed (its durable record, else its Redis hash says so)."""
        if self.ctx.store.jobs.is_finished(job_id):
            return True
        if jobs.read_job(self.ctx.r, self.ctx.prefix, job_id).get("state") in ("done", "failed"):
            self.finish_job(job_id)  # the record stayed open (a write failed after the job): close it now
            return True
        return False

    def finish_job(self, job_id: str, state: str | None = None) -> None:
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

    def dead_letter(self, stream: str, entry_id: str, fields: dict[str, str], error: str) -> None:
        """Move an entry to the dead-letter stream; a frame becomes poison (rejected), a job fails."""
        ctx = self.ctx
        log.error("dead-lettering an entry of kind %s: %s", fields.get("kind"), error[:200])
        kind, sid = fields.get("kind"), fields.get("session", "")
        # the durable mark first: if storage or Redis fails here, the entry stays pending and is retried
        if kind == "frame":
            try:
                ctx.version(sid).ensure(ctx.live_options())
            except (SessionNotFoundError, FileNotFoundError):
                kind = None  # the session is gone: nothing to mark
            else:
                ctx.results.mark_poison(sid, LIVE_VERSION, int(fields["seq"]), error)
                queue.mark_frame_handled(ctx.r, sid, int(fields["seq"]), ctx.prefix)
        entry = {**fields, "stream": stream, "entry": entry_id, "error": error[:300], "at": repr(time.time())}
        dead_letters.dead_letter(ctx.r, entry, ctx.prefix)
        if kind == "frame":
            queue.incr_metric(ctx.r, "frames_rejected_total", prefix=ctx.prefix)
            queue.enqueue_register(ctx.r, sid, LIVE_VERSION, ctx.prefix)
        elif kind in ("reprocess", "send") and fields.get("job"):
            ctx.update_job(fields["job"], state="failed", error=error[:300])
            if kind == "reprocess":
                queue.incr_metric(ctx.r, "jobs_failed_total", prefix=ctx.prefix)
            self.finish_job(fields["job"], "failed")
        queue.ack_delete(ctx.r, stream, entry_id)


def run_worker(
    data_dir: Path | str,
    redis_url: str | None = None,
    *,
    prefix: str = "vm:",
    consumer: str | None = None,
    stop: threading.Event | None = None,
    max_seconds: float | None = None,
    handle_signals: bool = True,
    max_frame_side: int = DEFAULT_MAX_FRAME_SIDE,
    config: WorkerConfig | None = None,
    **options: Any,
) -> int:
    """Return the exit code 0 after running one worker until SIGTERM/SIGINT (or `stop` is set, or max_seconds pass).

    config: the worker's configuration made from the settings (WorkerConfig.from_settings, what main() passes);
    without it one is made from data_dir, redis_url, prefix, consumer and `options`, any other WorkerSettings
    field (lost_timeout_s, lease_ms, flush_every_s, debug_order, ...; an unknown field is refused).

    max_frame_side (the settings' frame size cap) sets Pillow's pixel limit in this process and makes the
    store refuse a larger frame from its header, before any decode (OpenCV's cap is set by `services`).
    """
    if config is None:
        cfg_args: dict[str, Any] = {"data_dir": Path(data_dir), "redis_url": redis_url, "prefix": prefix, **options}
        if consumer:
            cfg_args["consumer"] = consumer
        config = WorkerConfig.model_validate(cfg_args)
    cfg = config
    set_decoder_limits(max_frame_side)
    r = connect(cfg.redis_url, cfg.data_dir)
    store = SessionStore(cfg.data_dir, max_frame_side=max_frame_side)
    ctx = Context(cfg, r, store, ResultsStore(cfg.data_dir), stop or threading.Event())
    if handle_signals and threading.current_thread() is threading.main_thread():

        def on_signal(_signum: int, _frame: object) -> None:
            ctx.stop.set()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
    try:
        Worker(ctx).run(max_seconds=max_seconds)
    finally:
        close(r)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Return the worker's argument parser; what it leaves out comes from services.settings.Settings."""
    p = argparse.ArgumentParser(prog="veinmosaic worker", description="Run one veinmosaic worker process.")
    p.add_argument("--data-dir", type=Path, default=None, help="default: VEINMOSAIC_DATA_DIR")
    p.add_argument("--redis-url", default=None, help="default: REDIS_URL (else the embedded server)")
    p.add_argument("--prefix", default=None, help="Redis key prefix; default VEINMOSAIC_REDIS_PREFIX or vm:")
    p.add_argument("--consumer", default=None, help="consumer name; default host:pid")
    p.add_argument(
        "--config-json",
        default=None,
        help='JSON of WorkerSettings fields, e.g. {"lost_timeout_s": 5}, over VEINMOSAIC_WORKER_CONFIG\'s',
    )
    p.add_argument("--lost-timeout-s", type=float, default=None, help="default: from the settings' worker_config")
    p.add_argument("--lease-ms", type=int, default=None, help="default: from the settings' worker_config")
    p.add_argument("--claim-idle-ms", type=int, default=None, help="default: from the settings' worker_config")
    p.add_argument("--max-seconds", type=float, default=None, help="exit after this long (tests)")
    p.add_argument("--heartbeat-file", default=None, help="touched every loop (at most every 2 s), for health checks")
    return p


def worker_config(args: argparse.Namespace, settings: Settings) -> WorkerConfig:
    """Return the worker's configuration: the settings, then --config-json's fields, then the single options."""
    overrides: dict[str, Any] = json.loads(args.config_json) if args.config_json else {}
    if not isinstance(overrides, dict):
        raise ValueError("--config-json: expected a JSON object of WorkerSettings fields")
    for name in ("lost_timeout_s", "lease_ms", "claim_idle_ms", "heartbeat_file"):
        overrides[name] = getattr(args, name)
    for name in ("data_dir", "redis_url", "prefix", "consumer"):
        if getattr(args, name) is not None:
            overrides[name] = getattr(args, name)
    return WorkerConfig.from_settings(settings, **overrides)


def main(argv: Sequence[str] | None = None) -> int:
    """Return the exit code of a worker run as services.settings.Settings (read once, here) and the command line say."""
    from services.log_format import configure_json_logging

    args = build_parser().parse_args(argv)
    settings = Settings()
    configure_json_logging(str(settings.log_level))
    if settings.worker_nice:
        with contextlib.suppress(OSError):
            os.nice(settings.worker_nice)  # ingest (API) before processing when the CPU is short
    cv2.setNumThreads(settings.worker_cv_threads)
    config = worker_config(args, settings)
    return run_worker(
        config.data_dir,
        config.redis_url,
        max_seconds=args.max_seconds,
        max_frame_side=settings.max_frame_side,
        config=config,
    )


if __name__ == "__main__":
    raise SystemExit(main())
