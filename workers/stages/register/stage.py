"""The register stage: the sessions this worker holds, each served by its named steps in order.

One worker at a time holds the lease of (session, version) and keeps the session's SessionReconstruction in
memory; it keeps the lease while the session is active (so the state is not rebuilt on every kick) and serves
its sessions between reads of the queue. Serving a session (`step`) is: renew the lease, register the frames
that are ready (cursor), run its finish ahead when due (ahead), complete the session once its last frame is in
(completion), flush when due (flush), release the lease when idle (lease). Taking a session over replays it
from state.json (cursor).

An infrastructure fault while serving a session (a write refused by a full disk, Redis unreachable) drops the
in-memory state and hands the lease off with a delay (or, Redis being down, lets it expire): the next holder
replays from the last durable state.json, so nothing half-written is ever published under a stale fence.
"""

from __future__ import annotations

import logging
import time

from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
from services.core.pipeline import window_radius_mm
from services.core.session_reconstruction import SessionReconstruction
from services.jobs.leases import Lease
from services.store.results_store import LIVE_VERSION
from services.store.storage import SessionNotFoundError
from workers.config import Context
from workers.faults import describe, failure_frames, failure_reason, is_transient
from workers.publisher import Publisher
from workers.stages.register.ahead import FinishAhead
from workers.stages.register.completion import Completion
from workers.stages.register.cursor import Cursor
from workers.stages.register.flush import Flusher
from workers.stages.register.held import HeldSession
from workers.stages.register.lease import LeaseKeeper, LeaseLostError
from workers.stages.register.poison import PoisonCounter

log = logging.getLogger("veinmosaic.worker")
IDLE_REPAINT = 16  # moved frames re-pasted per step of a session that caught up with its uploads


class RegisterStage:
    """The sessions this worker holds, and the handling of registration kicks."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx
        self.publisher = Publisher(ctx)
        self.leases = LeaseKeeper(ctx)
        self.flusher = Flusher(ctx, self.publisher, self.leases)
        self.completion = Completion(ctx, self.publisher, self.leases, self.flusher)
        self.cursor = Cursor(ctx, self.leases, self.flusher, PoisonCounter(ctx))
        self.ahead = FinishAhead(ctx, self.publisher)
        self.held: dict[tuple[str, int], HeldSession] = {}
        self.faulted = False  # a held session met an infrastructure fault during the current step

    # ----- entry points ---------------------------------------------------------------------------------------
    def on_kick(self, sid: str, version: int) -> None:
        """Handle a kick: serve the session when this worker holds it or can take it; else flag the holder."""
        held = self.held.get((sid, int(version)))
        if held is None:
            lease = self.leases.take(sid, version)
            if lease is None:
                return  # the holder will see the kick flag before it releases
            try:
                held = self.take_over(lease)
            except BaseException:
                lease.release(self.ctx.r, mode="final")  # the kick is retried (then dead-lettered) by the loop
                raise
            if held is None:
                return
            self.held[held.key] = held
        self.serve(held)

    def poll(self) -> None:
        """Serve every held session once (see `step`)."""
        for held in list(self.held.values()):
            if self.ctx.stop.is_set():
                return
            self.serve(held)

    def release_all(self) -> None:
        """Flush and release every held session (graceful stop); another worker takes over."""
        for key, held in list(self.held.items()):
            try:
                if held.pending.dirty:
                    self.flusher.flush(held, final=False)
                held.lease.release(self.ctx.r, mode="handoff")
            except (LeaseLostError, SessionNotFoundError):
                pass
            except Exception:  # keep releasing the others
                log.exception("release on stop failed")
            self.held.pop(key, None)

    # ----- one session ----------------------------------------------------------------------------------------
    def step(self, held: HeldSession) -> bool:
        """Return False once the session is not held any more, else True, serving a held session once.

        In order: renew the lease, register the frames that are ready, run the finish ahead when due, complete the
        session once its last frame is in, flush when due, release it when idle.
        """
        self.leases.renew_if_due(held, force=True)
        meta = self.ctx.store.get_meta(held.sid)
        finished = meta.finished_at is not None
        caught_up = self.cursor.register_ready(held, finished)
        if self.ahead.due(held, caught_up, finished, time.monotonic()):
            self.ahead.run(held)
        if caught_up and held.recon.stale:  # idle between frames: repaint what a refinement or a run ahead moved
            held.pending.touched |= held.recon.settle(IDLE_REPAINT)
            held.pending.dirty = True
        if finished and not self.ctx.stop.is_set() and self.cursor.at_end(held):
            self.completion.complete(held, meta.status)
            held.lease.release(self.ctx.r, mode="final")
            return False
        now = time.monotonic()
        if held.pending.dirty and self.flusher.due(held, now):
            self.flusher.flush(held, final=False, caught_up=caught_up)
        if self.leases.idle(held, now):
            if held.pending.dirty:
                self.flusher.flush(held, final=False, caught_up=caught_up)
            if held.lease.release(self.ctx.r) == 0:
                return True  # refused: work arrived meanwhile, keep serving
            log.info(
                "session released after %.0f s without progress",
                now - held.clocks.progressed,
                extra={"session": held.sid},
            )
            return False
        return True

    def serve(self, held: HeldSession) -> None:
        """Run `step` on a held session; drop it when it is no longer held, gone, or met a fault."""
        try:
            if not self.step(held):
                self.held.pop(held.key, None)
        except LeaseLostError:
            log.warning("lease lost; dropping the session's in-memory state", extra={"session": held.sid})
            self.held.pop(held.key, None)
        except SessionNotFoundError:
            self.held.pop(held.key, None)
            held.lease.release(self.ctx.r, mode="final")
        except Exception as exc:
            self.fault(held, exc)

    def fault(self, held: HeldSession, exc: Exception) -> None:
        """Drop a session after a fault; hand the lease off after a delay, or let it expire if Redis is down."""
        self.faulted = True
        self.held.pop(held.key, None)
        if is_transient(exc):
            log.warning("infrastructure fault (%s); session handed off", describe(exc), extra={"session": held.sid})
        else:
            log.error(
                "serving a session failed (%s); handed off\n%s",
                failure_reason(exc),
                failure_frames(exc),
                extra={"session": held.sid},
            )
        self.leases.hand_off_after_fault(held)

    # ----- take-over ------------------------------------------------------------------------------------------
    def take_over(self, lease: Lease) -> HeldSession | None:
        """Return the session of a lease just taken, its reconstruction replayed from state.json; None when there
        is nothing to serve (gone, finished, fenced out, or no setup yet: then the lease is released)."""
        ctx = self.ctx
        try:
            meta = ctx.store.get_meta(lease.session_id)
        except SessionNotFoundError:
            lease.release(ctx.r, mode="final")
            return None
        sv = ctx.version(lease.session_id, lease.version)
        sv.ensure(ctx.live_options())
        state = sv.state()
        if self.leases.fenced_out(state, lease):
            lease.release(ctx.r, mode="handoff", handoff_delay_s=1.0)
            return None
        if state.finished:
            if sv.v == LIVE_VERSION and meta.status not in ("done", "failed"):
                ctx.store.set_status(sv.sid, "done")
            lease.release(ctx.r, mode="final")
            return None
        setup = ctx.results.read_setup(sv.sid, sv.v)
        if setup is None:
            seqs = sv.stored_seqs()
            if meta.finished_at is not None and all(sv.is_poison(s) for s in seqs):
                self.completion.finish_empty(lease, sv, meta.status, seqs)
            else:
                lease.release(ctx.r, mode="final")  # the next prepared frame kicks again
            return None
        calib = sv.calibration
        recon = SessionReconstruction(
            calib,
            sv.method_options,
            window_radius_mm(setup[0], calib),
            live=True,
            pixels=sv.prepared_pixels,  # a frame's index is its seq; its pixels stay on disk, not in the worker
        )
        geometry = DziGeometry.for_mosaic(calib.px_per_mm, ctx.config.half_extent_mm)
        held = HeldSession(
            sv, lease, recon, geometry, TilePyramid(geometry), lost=list(state.lost), rejected=list(state.rejected)
        )
        held.clocks.renewed = time.monotonic()
        recon.heartbeat = lambda: self.leases.renew_if_due(held)  # the lease outlives a long refinement or repaint
        self.cursor.replay(held, state.cursor)
        return held
