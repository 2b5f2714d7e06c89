"""Dispatch: which stage an entry of the worker streams belongs to (its "kind"), and whether this worker takes a
session's kick or leaves it to a less loaded one."""

from __future__ import annotations

import logging

from services.jobs import worker_load
from services.store.results_store import LIVE_VERSION
from workers.config import Context
from workers.jobs.runner import JobRunner
from workers.retry import Retry
from workers.stages.prepare import handle_frame
from workers.stages.register import RegisterStage

log = logging.getLogger("veinmosaic.worker")

# A kick declined by a worker busier than another (Dispatcher.busier_than_another) comes back after this long, for
# the less loaded worker to take; short, so a new session waits a fraction of a second at most once or twice.
DECLINE_DELAY_S = 0.2


class Dispatcher:
    """Runs an entry's stage: a frame is prepared, a kick taken by the register stage, a job run by the runner."""

    def __init__(self, ctx: Context, register: RegisterStage, runner: JobRunner) -> None:
        self.ctx = ctx
        self.register = register
        self.runner = runner

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
            return self.runner.run(stream, entry_id, fields)
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
