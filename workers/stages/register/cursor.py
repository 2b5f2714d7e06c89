"""The cursor and replay: a held session's frames go to registration one by one, in seq order, exactly once.

The cursor is the next seq to register. A poison frame is registered as rejected, a prepared one added; a frame
stored but not prepared yet is waited for (its job re-queued if it seems to have vanished); a frame never
stored is lost once a later one has waited lost_timeout_s (or the session is finished). A worker taking a
session over replays frames [0, cursor) the same way from the prepared files and state.json's lost and
rejected seqs: registration is deterministic, so the result is the one a single worker would have made.
"""

from __future__ import annotations

import logging
import time

from services.core.registration.frame_prep import PreparedFrame
from services.jobs import queue
from workers.config import Context
from workers.stages.register.flush import Flusher
from workers.stages.register.held import HeldSession
from workers.stages.register.lease import LeaseKeeper, LeaseLostError
from workers.stages.register.poison import PoisonCounter

log = logging.getLogger("veinmosaic.worker")


class Cursor:
    """Moves held sessions' cursors: frames registered as they become available, or replayed after a take-over."""

    def __init__(self, ctx: Context, leases: LeaseKeeper, flusher: Flusher, poison: PoisonCounter) -> None:
        self.ctx = ctx
        self.leases = leases
        self.flusher = flusher
        self.poison = poison

    def replay(self, held: HeldSession, cursor: int) -> None:
        """Rebuild the reconstruction from frames [0, cursor) in order (deterministic), then the tile pyramid."""
        lost, rejected = set(held.lost), set(held.rejected)
        for seq in range(cursor):
            self.leases.renew_if_due(held)
            if seq in lost:
                self._lose(held, seq, replay=True)
            elif seq in rejected:
                self._reject(held, seq, replay=True)
            else:
                pf = held.sv.prepared(seq)
                if pf is None:  # cannot happen unless files were removed: record it as lost
                    self._lose(held, seq, replay=True)
                    held.lost.append(seq)
                else:
                    self._add(held, pf, replay=True)
        held.cursor = cursor
        held.replayed = cursor > 0
        held.clocks.progressed = time.monotonic()  # the replay was progress: not idle since the take-over
        held.pyramid.update(held.recon.canvas, set(held.recon.canvas.tiles))
        held.pending.touched.clear()
        held.pending.seqs.clear()
        # counters are idempotent per seq: re-record all, in case the previous holder died before counting
        self.flusher.record_counters(held, list(range(cursor)))
        log.info("session taken over at cursor %d (token %d)", cursor, held.lease.token, extra={"session": held.sid})

    def register_ready(self, held: HeldSession, finished: bool) -> bool:
        """Return True when caught up with the uploads, False when frames uploaded are still to be placed.

        It registers frames from the cursor while they are available (for at most pass_budget_s), flushing when due.
        """
        ctx, cfg, sv = self.ctx, self.ctx.config, held.sv
        started = time.monotonic()
        seqs: list[int] | None = None
        while not ctx.stop.is_set() and time.monotonic() - started < cfg.pass_budget_s:
            seq = held.cursor
            if sv.is_poison(seq):
                self._reject(held, seq)
                held.rejected.append(seq)
                self._advance(held)
                continue
            pf = sv.prepared(seq)
            if pf is not None:
                try:
                    self._add(held, pf)
                except Exception as exc:
                    self.poison.registration_failed(held, seq, exc)
                    raise LeaseLostError from exc
                self._advance(held)
                if self.flusher.due(held):
                    self.flusher.flush(held, final=False, caught_up=False)
                self.leases.renew_if_due(held)
                continue
            rec = ctx.store.get_frame(sv.sid, seq)
            if rec is not None:  # stored, not prepared yet: wait; re-queue if its job seems to have vanished
                if time.time() - rec.received_at > cfg.lost_timeout_s:
                    every_ms = int(1000 * max(cfg.lost_timeout_s, 5.0))  # idempotent, so a duplicate costs little
                    queue.requeue_frame(ctx.r, sv.sid, seq, ctx.prefix, at_most_every_ms=every_ms)
                return False  # behind: the frame is uploaded, its preparation is not done
            seqs = sv.stored_seqs() if seqs is None or seqs[-1:] <= [seq] else seqs
            later = [s for s in seqs if s > seq]
            if not later:
                return True
            if not finished:
                nxt = ctx.store.get_frame(sv.sid, later[0])
                if nxt is None or time.time() - nxt.received_at <= cfg.lost_timeout_s:
                    return True
            self._lose(held, seq)
            held.lost.append(seq)
            self._advance(held)
        return False

    def at_end(self, held: HeldSession) -> bool:
        """Return True when the cursor is past the last stored frame (or none is stored)."""
        seqs = held.sv.stored_seqs()
        return not seqs or held.cursor > seqs[-1]

    # ----- one frame -------------------------------------------------------------------------------------------
    def _advance(self, held: HeldSession) -> None:
        held.cursor += 1
        held.pending.dirty = True
        held.clocks.progressed = time.monotonic()

    def _log_order(self, held: HeldSession, seq: int, kind: str) -> None:
        if self.ctx.config.debug_order:
            queue.log_order(self.ctx.r, held.sid, held.version, f"{held.lease.token}:{seq}:{kind}", self.ctx.prefix)

    def _add(self, held: HeldSession, pf: PreparedFrame, replay: bool = False) -> None:
        self._log_order(held, pf.seq, "add")
        started = time.process_time()  # the process's: a re-paste warps on helper threads
        result, touched = held.recon.add(pf, repaint=replay or not held.behind)  # far behind: moved frames wait
        if not replay:
            held.pending.cost.add(held.recon.frame_kind(pf.index), time.process_time() - started)
            held.pending.touched |= touched
            held.pending.seqs.append(pf.seq)
            if result.moved:
                held.pending.path_reset = True

    def _lose(self, held: HeldSession, seq: int, replay: bool = False) -> None:
        self._without_frame(held, seq, "lost", replay)

    def _reject(self, held: HeldSession, seq: int, replay: bool = False) -> None:
        self._without_frame(held, seq, "rejected", replay)

    def _without_frame(self, held: HeldSession, seq: int, kind: str, replay: bool) -> None:
        """Register `seq` as lost or rejected (no prepared frame), with its stored time when it has one."""
        self._log_order(held, seq, kind)
        if kind == "lost":
            held.recon.lose(seq)
        else:
            held.recon.reject(seq)
        t_s = held.sv.frame_t_s(seq)
        if t_s is not None:
            held.times[seq] = t_s
        if not replay:
            held.pending.seqs.append(seq)
