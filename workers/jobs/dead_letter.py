"""Dead letters: an entry that failed too often leaves the work list for <prefix>dead (services.jobs.dead_letters);
a frame becomes poison (registered as rejected), a job fails and its record is closed."""

from __future__ import annotations

import logging
import time

from services.jobs import dead_letters, queue
from services.store.results_store import LIVE_VERSION
from services.store.storage import SessionNotFoundError
from workers.config import Context
from workers.jobs.runner import JobRunner

log = logging.getLogger("veinmosaic.worker")


def dead_letter(
    ctx: Context, runner: JobRunner, stream: str, entry_id: str, fields: dict[str, str], error: str
) -> None:
    """Move an entry to the dead-letter stream; a frame becomes poison (rejected), a job fails."""
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
        if kind == "reprocess":  # counted before the state a client waits for
            queue.incr_metric(ctx.r, "jobs_failed_total", prefix=ctx.prefix)
        ctx.update_job(fields["job"], state="failed", error=error[:300])
        runner.finish(fields["job"], "failed")
    queue.ack_delete(ctx.r, stream, entry_id)
