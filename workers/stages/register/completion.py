"""Completion: a finished session's last frame is registered, so the version is finalised and the session done.

complete: the reconstruction's final refinement and compliance fit, then the final flush (the tiles that changed,
then every tile made durable at once, the whole images and raw layers; every tile written again when the session
was taken over mid-way). finish_empty: a finished session with no usable frame (none, or all poison)
gets its rows (all rejected) and an empty mosaic. Either way the live session's status becomes done.
"""

from __future__ import annotations

import logging
import time

from services.core.mosaic.deepzoom import DziGeometry
from services.core.outputs.documents import empty_image_meta, empty_revisions
from services.jobs.leases import Lease
from services.store.results_store import LIVE_VERSION
from services.store.session_version import SessionVersion
from services.store.version_state import VersionState
from workers.config import Context
from workers.publisher import Publisher
from workers.stages.register.flush import Flusher
from workers.stages.register.held import HeldSession
from workers.stages.register.lease import LeaseKeeper

log = logging.getLogger("veinmosaic.worker")


class Completion:
    """Finishes held sessions whose frames are all registered, and finished sessions with no usable frame."""

    def __init__(self, ctx: Context, publisher: Publisher, leases: LeaseKeeper, flusher: Flusher) -> None:
        self.ctx = ctx
        self.publisher = publisher
        self.leases = leases
        self.flusher = flusher

    def complete(self, held: HeldSession, session_status: str) -> None:
        """Final refinement and compliance fit, final flush and render, status done."""
        self.leases.renew_if_due(held, force=True)
        self.leases.check_fence(held)
        started = time.monotonic()
        held.pending.touched |= held.recon.finish()  # the tiles of the frames the finish moved
        if held.replayed:  # the previous holder's tiles may be lost with its machine: all written again
            held.pending.touched |= set(held.recon.canvas.tiles)
        finished = time.monotonic()

        def mark_done() -> None:  # after every file is written, before the final event: no client sees it early
            if held.version == LIVE_VERSION and session_status != "failed":
                self.ctx.store.set_status(held.sid, "done")

        flushed = self.flusher.flush(held, final=True, before_event=mark_done)
        flush_s = time.monotonic() - finished
        timings = {"finish_s": round(finished - started, 2), "final_flush_s": round(flush_s, 2)}
        parts = {**held.recon.finish_seconds, **{f"flush_{k}": v for k, v in flushed.items()}}
        if held.version == LIVE_VERSION:
            finish = {**held.recon.finish_seconds, "final_flush": flush_s}
            self.publisher.count_finish(finish, held.recon.finish_pasted_again)
        log.info(
            "session done",
            extra={
                "session": held.sid,
                "frames": len(held.recon.results),
                **timings,
                "parts_s": parts,
                "pasted_again": held.recon.finish_pasted_again,
                "unstitched": len(held.recon.unstitched),
            },
        )

    def finish_empty(self, lease: Lease, sv: SessionVersion, session_status: str, rejected: list[int]) -> None:
        """A finished session with no usable frame (none, or all poison): rows rejected, no mosaic, status done."""
        ctx, pub, sid, v = self.ctx, self.publisher, sv.sid, sv.v
        rejected = sorted(rejected)
        calib = sv.calibration
        geometry = DziGeometry.for_mosaic(calib.px_per_mm, ctx.config.half_extent_mm)
        rows = [sv.rejected_row(seq) for seq in rejected]
        pub.write_path(sid, v, rows)
        doc = pub.write_mosaic_json(
            sid,
            v,
            empty_image_meta(calib.px_per_mm),
            version=1,
            revisions=empty_revisions(),
            geometry=geometry,
            extent_mm=None,
            rows=rows,
            status="done",
            method=sv.method_options.name,
        )
        cursor = rejected[-1] + 1 if rejected else 0
        pub.write_state(sid, v, VersionState(cursor=cursor, fence=lease.token, finished=True, rejected=rejected))
        pub.count_frames(sid, v, [(seq, True) for seq in rejected])
        if session_status != "failed":
            ctx.store.set_status(sid, "done")  # before the event, as in complete
        pub.results_event(sid, doc, {}, rows, rejected, path_reset=True)
        lease.release(ctx.r, mode="final")
