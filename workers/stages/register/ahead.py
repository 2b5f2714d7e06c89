"""The finish run ahead: while a live scan goes on, its finish is run now and then on a copy of the session, and the
canvas kept at the places it gives, so that the session is done soon after its last upload (the real finish then
pastes again only the frames that moved since: SessionReconstruction.run_ahead).

A run is due once the session has caught up with its uploads, is not finished, has re-pasted every frame waiting to
be (the last run's moved frames among them), has placed new frames since the last run, and finish_ahead_every_s (or
AHEAD_COST_FACTOR times the last run's duration, if longer: a long examination's run takes about 2 s at 2400
frames) has passed since it; finish_ahead_every_s 0 (the default) turns it off: the canvas's units take up the
compliance gauge's change, but each run still moves hundreds of frames of a long examination beyond that
(docs/performance.md).
"""

from __future__ import annotations

import logging
import time

from workers.config import Context
from workers.publisher import Publisher
from workers.stages.register.held import HeldSession

log = logging.getLogger("veinmosaic.worker")
AHEAD_COST_FACTOR = 5.0  # runs ahead take at most a fifth of a session's time


class FinishAhead:
    """Runs held live sessions' finishes ahead of their ends when due."""

    def __init__(self, ctx: Context, publisher: Publisher) -> None:
        self.ctx = ctx
        self.publisher = publisher

    def due(self, held: HeldSession, caught_up: bool, finished: bool, now: float) -> bool:
        """Return True when a run ahead is due: caught up, not finished, nothing waiting to be re-pasted, new frames
        placed, the interval passed."""
        every = self.ctx.config.finish_ahead_every_s
        return (
            every > 0
            and caught_up
            and not finished
            and not held.recon.stale  # the last run's moved frames are re-pasted (the idle settle) before another
            and len(held.recon.registrar.order) > held.clocks.ahead_placed
            and now - held.clocks.ahead >= max(every, held.clocks.ahead_interval)
        )

    def run(self, held: HeldSession) -> None:
        """Run the finish ahead on a copy of the session; its moved frames wait to be re-pasted (settle), and the
        next flush tells clients to re-read the path (now in the run's units)."""
        started, cpu = time.monotonic(), time.process_time()
        stale = held.recon.run_ahead()
        self.publisher.count_finish_ahead(time.process_time() - cpu)
        held.pending.path_reset = True
        held.pending.dirty = True
        held.clocks.ahead = time.monotonic()
        held.clocks.ahead_interval = AHEAD_COST_FACTOR * (held.clocks.ahead - started)
        held.clocks.ahead_placed = len(held.recon.registrar.order)
        log.debug(
            "finish run ahead",
            extra={"session": held.sid, "seconds": round(held.clocks.ahead - started, 3), "stale": stale},
        )
