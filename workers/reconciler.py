"""The reconciler: durable storage is the truth, Redis only the work list. Re-enqueue what Redis forgot.

Redis may lose its last second of AOF, or be wiped. Then an upload that is durable on disk (and was answered
2xx) may have no job left. The reconciler compares the two: every stored frame of a session that is not
done must have a result (a prepared file or a poison mark of the live version) or a job (an entry of the
frames stream or of the delayed set, read in one MULTI snapshot); those with neither are enqueued again, and
registration is kicked for sessions with work nobody holds. A done session whose Redis counters are gone gets
them rebuilt from its path. Reprocess jobs likewise: every job answered 202 has an open record in the job
ledger (data_dir/jobs) until it is done or failed; an open record whose job is neither on the jobs stream
(pending entries included) nor delayed is enqueued again from the record, unless Redis still says the job
finished (then the record is closed). Re-enqueueing is safe because every job is idempotent (prepared frames are
write-once, counters are counted once per seq), so a frame is processed exactly once even when a race
enqueues it twice.

One worker at a time runs it (a short Redis lock), at start-up, after Redis restarted (its run_id changed)
and every reconcile_every_s (a second key, SET NX PX, spaces the periodic runs across all workers).
"""

from __future__ import annotations

import json
import logging
import time
from typing import Any

from services.jobs import job_lanes, queue, reconcile_turn
from services.jobs import job_records as jobs
from services.store.results_store import LIVE_VERSION
from services.store.storage import SessionNotFoundError
from workers.config import Context

log = logging.getLogger("veinmosaic.worker")


def _text(v: Any) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def known_frame_jobs(ctx: Context) -> set[tuple[str, int]]:
    """Return (session, seq) of every frame job on the frames stream or in the delayed set (one snapshot)."""
    pipe = ctx.r.pipeline(transaction=True)
    pipe.xrange(queue.frames_stream(ctx.prefix), "-", "+")
    pipe.zrange(queue.delayed_key(ctx.prefix), 0, -1)
    entries, delayed_members = pipe.execute()
    known: set[tuple[str, int]] = set()
    for _eid, fields in entries or []:
        f = {_text(k): _text(v) for k, v in fields.items()}
        if f.get("kind") == "frame" and f.get("seq", "").isdigit():
            known.add((f.get("session", ""), int(f["seq"])))
    for member in delayed_members or []:
        try:
            job = json.loads(_text(member))
            f = job["f"]
            if job["s"] == queue.frames_stream(ctx.prefix) and f.get("kind") == "frame":
                known.add((str(f.get("session", "")), int(f["seq"])))
        except (ValueError, KeyError, TypeError):
            continue
    return known


def reconcile(ctx: Context) -> dict[str, int]:
    """Return the counts of one reconciliation (sessions, frames_requeued, kicks, counters_rebuilt, jobs_requeued).

    It re-enqueues stored frames with no job and no result, kicks unheld sessions, rebuilds lost counters.
    """
    started = time.monotonic()
    queue.ensure_groups(ctx.r, ctx.prefix)
    known = known_frame_jobs(ctx)
    stats = {"sessions": 0, "frames_requeued": 0, "kicks": 0, "counters_rebuilt": 0}
    for sid in ctx.store.list_sessions():
        try:
            meta = ctx.store.get_meta(sid)
        except (SessionNotFoundError, ValueError, OSError):
            continue
        stats["sessions"] += 1
        if meta.status in ("done", "failed"):
            stats["counters_rebuilt"] += _rebuild_counters(ctx, sid)
            continue
        sv = ctx.version(sid)
        handled = sv.handled_seqs()
        missing = [s for s in sv.stored_seqs() if s not in handled and (sid, s) not in known]
        for seq in missing:
            queue.requeue_frame(ctx.r, sid, seq, ctx.prefix)
        stats["frames_requeued"] += len(missing)
        state = sv.state()
        pending = meta.finished_at is not None or any(s >= state.cursor for s in handled)
        if pending and not state.finished and not ctx.r.exists(queue.lease_key(sid, LIVE_VERSION, ctx.prefix)):
            queue.enqueue_register(ctx.r, sid, LIVE_VERSION, ctx.prefix)
            stats["kicks"] += 1
    stats["jobs_requeued"] = reconcile_jobs(ctx)
    if stats["frames_requeued"]:
        queue.incr_metric(ctx.r, "reconciled_frames_total", stats["frames_requeued"], prefix=ctx.prefix)
    if stats["jobs_requeued"]:
        queue.incr_metric(ctx.r, "reconciled_jobs_total", stats["jobs_requeued"], prefix=ctx.prefix)
    queue.incr_metric(ctx.r, "reconcile_runs_total", prefix=ctx.prefix)
    acted = stats["frames_requeued"] or stats["kicks"] or stats["counters_rebuilt"] or stats["jobs_requeued"]
    log.log(
        logging.INFO if acted else logging.DEBUG,
        "reconciled %d sessions: %d frames re-enqueued, %d registration kicks, %d counter sets rebuilt, "
        "%d reprocess jobs re-enqueued (%.0f ms)",
        stats["sessions"],
        stats["frames_requeued"],
        stats["kicks"],
        stats["counters_rebuilt"],
        stats["jobs_requeued"],
        1000 * (time.monotonic() - started),
    )
    return stats


def reconcile_jobs(ctx: Context) -> int:
    """Return how many reprocess jobs with an open ledger record that Redis no longer holds were re-enqueued."""
    records = ctx.store.jobs.open_jobs()
    if not records:
        return 0
    known = job_lanes.known_jobs(ctx.r, ctx.prefix)  # in a key's lane, on the stream or delayed
    requeued = 0
    for record in records:
        job_id = record.get("id", "")
        if not job_id or job_id in known:
            continue
        state = jobs.read_job(ctx.r, ctx.prefix, job_id).get("state", "")
        if state in ("done", "failed"):  # it finished; only the record's closing was lost
            ctx.store.jobs.finish(job_id, state)
            continue
        jobs.requeue_job(ctx.r, ctx.prefix, record)
        requeued += 1
    return requeued


def _rebuild_counters(ctx: Context, sid: str) -> int:
    """Re-count a finished live run's frames from its path when Redis lost the session's counters; 1 if done."""
    if ctx.r.exists(queue.session_key(sid, ctx.prefix)):
        return 0
    rows = ctx.results.read_path(sid, LIVE_VERSION) if ctx.version(sid).state().finished else None
    if not rows:
        return 0
    counted = lost = 0
    for row in rows:
        is_lost = row.get("status") != "ok"
        if queue.record_frame_result(ctx.r, sid, int(row["seq"]), is_lost, ctx.prefix):
            counted += 1
            lost += is_lost
    return 1 if counted else 0


class Reconciler:
    """Decides when this worker runs the reconciler: at start, after a Redis restart, and periodically."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx
        self.run_id: str | None = None
        self.next_check = 0.0
        self.urgent = True  # at start-up

    def maybe_run(self) -> dict[str, int] | None:
        """Return the reconciler's stats when it ran (due, and this worker won the lock), else None."""
        ctx, cfg = self.ctx, self.ctx.config
        now = time.monotonic()
        if now < self.next_check and not self.urgent:
            return None
        self.next_check = now + min(5.0, cfg.reconcile_every_s or 5.0)
        run_id = str(ctx.r.info("server").get("run_id", ""))
        if self.run_id is not None and run_id != self.run_id:
            log.warning("redis restarted (new run id): reconciling storage with the queue")
            self.urgent = True
        self.run_id = run_id
        period_ms = max(1, int(1000 * cfg.reconcile_every_s))
        if not self.urgent:
            if cfg.reconcile_every_s <= 0:
                return None
            if not reconcile_turn.claim_periodic_run(ctx.r, ctx.prefix, cfg.consumer, period_ms):
                return None
        elif cfg.reconcile_every_s > 0:
            reconcile_turn.mark_run(ctx.r, ctx.prefix, cfg.consumer, period_ms)
        if not reconcile_turn.acquire_lock(ctx.r, ctx.prefix, cfg.consumer):
            self.urgent = False  # another worker is reconciling right now
            return None
        try:
            stats = reconcile(ctx)
        finally:
            reconcile_turn.release_lock(ctx.r, ctx.prefix, cfg.consumer)
        self.urgent = False
        return stats
