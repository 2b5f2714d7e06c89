"""Stage 2: register prepared frames of a session in seq order, under a lease, and publish the results.

One worker at a time holds the lease of (session, version) and keeps the session's SessionReconstruction in
memory; it keeps the lease while the session is active (so the state is not rebuilt on every kick) and polls
its sessions between reads of the queue. A worker that takes a session over (new, released or crashed
holder) rebuilds the reconstruction by replaying the prepared frames [0, cursor) in order: registration is
deterministic, so the result is the same as if one process had done everything. Before every durable write
the holder checks its fence (its lease value in Redis, and the token in state.json not newer than its own).
Flushes (path.json, changed tiles, mosaic.json, state.json, counters, one event) happen at most every
flush_every_s; the whole mosaic.png/force.png at most every image_every_s; both at the end.

An infrastructure fault while serving a session (a write refused by a full disk, Redis unreachable) drops the
in-memory state and hands the lease off with a delay (or, Redis being down, lets it expire): the next holder
replays from the last durable state.json, so nothing half-written is ever published under a stale fence.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import redis

from services.core.calibration import Calibration
from services.core.deepzoom import DziGeometry, TilePyramid
from services.core.method_options import apply_calibration, parse_options
from services.core.methods import MethodOptions
from services.core.pipeline import window_radius_mm
from services.core.registrar import STATUS_OK
from services.core.results_docs import canvas_extent_mm, empty_image_meta, empty_revisions, image_meta, rejected_row
from services.core.session_reconstruction import PathRow, SessionReconstruction
from services.jobs import queue
from services.jobs.leases import Lease, acquire
from services.store.results_store import LIVE_VERSION
from services.store.storage import SessionNotFoundError
from workers.config import Context
from workers.faults import describe, is_transient
from workers.publisher import Publisher
from workers.stages.prepare import stored_seqs

log = logging.getLogger("veinmosaic.worker")


class LeaseLostError(Exception):
    """Another worker holds (or took) the session: stop without writing."""


@dataclass
class HeldSession:
    """A session whose lease this worker holds, with its in-memory reconstruction and publishing state."""

    sid: str
    version: int
    lease: Lease
    calib: Calibration
    options: MethodOptions
    recon: SessionReconstruction
    geometry: DziGeometry
    pyramid: TilePyramid
    cursor: int = 0
    lost: list[int] = field(default_factory=list)
    rejected: list[int] = field(default_factory=list)
    times: dict[int, float] = field(default_factory=dict)  # t_s of frames registered without a PreparedFrame
    touched: set[tuple[int, int]] = field(default_factory=set)
    unreported: list[int] = field(default_factory=list)  # seqs handled since the last flush
    path_reset: bool = False  # an earlier frame moved (refinement): clients should re-read the path
    dirty: bool = False
    done: bool = False
    last_flush: float = 0.0
    flush_interval: float = 0.0  # max(flush_every_s, 2 x the last flush's duration): flushing stays <= 1/3
    deferred: set[tuple[int, int, int]] = field(default_factory=set)  # whole-canvas levels, rendered with images
    last_image: float = 0.0
    last_renew: float = 0.0
    last_progress: float = field(default_factory=time.monotonic)


class RegisterStage:
    """The sessions this worker holds, and the handling of registration kicks."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx
        self.publisher = Publisher(ctx)
        self.held: dict[tuple[str, int], HeldSession] = {}
        self.faulted = False  # a held session met an infrastructure fault during the current step

    # ----- entry points ---------------------------------------------------------------------------------------
    def on_kick(self, sid: str, version: int) -> None:
        """Handle a kick: run a pass when this worker holds the session or can take it; else flag the holder."""
        key = (sid, int(version))
        held = self.held.get(key)
        if held is None:
            cfg = self.ctx.config
            lease = acquire(self.ctx.r, sid, version, cfg.consumer, cfg.lease_ms, self.ctx.prefix)
            if lease is None:
                return  # the holder will see the kick flag before it releases
            try:
                held = self._take_over(lease)
            except BaseException:
                lease.release(self.ctx.r, mode="final")  # the kick is retried (then dead-lettered) by the loop
                raise
            if held is None:
                return
            self.held[key] = held
        self._run(held)

    def poll(self) -> None:
        """Serve every held session: renew, register what became available, flush when due, release idle ones."""
        for held in list(self.held.values()):
            if self.ctx.stop.is_set():
                return
            self._run(held)

    def release_all(self) -> None:
        """Flush and release every held session (graceful stop); another worker takes over."""
        for key, held in list(self.held.items()):
            try:
                if held.dirty:
                    self._flush(held, final=False)
                held.lease.release(self.ctx.r, mode="handoff")
            except (LeaseLostError, SessionNotFoundError):
                pass
            except Exception:  # keep releasing the others
                log.exception("release on stop failed")
            self.held.pop(key, None)

    # ----- take-over and replay ------------------------------------------------------------------------------
    def _take_over(self, lease: Lease) -> HeldSession | None:
        ctx, sid, v = self.ctx, lease.session_id, lease.version
        try:
            meta = ctx.store.get_meta(sid)
        except SessionNotFoundError:
            lease.release(ctx.r, mode="final")
            return None
        ctx.results.ensure_version(sid, v, {"method": ctx.config.method, "source": "live"})
        state = ctx.results.read_state(sid, v) or {}
        if int(state.get("fence", 0)) > lease.token:
            lease.release(ctx.r, mode="handoff", handoff_delay_s=1.0)
            return None
        if state.get("finished"):
            if v == LIVE_VERSION and meta.status not in ("done", "failed"):
                ctx.store.set_status(sid, "done")
            lease.release(ctx.r, mode="final")
            return None
        setup = ctx.results.read_setup(sid, v)
        if setup is None:
            seqs = stored_seqs(ctx, sid)
            if meta.finished_at is not None and all(ctx.results.is_poison(sid, v, s) for s in seqs):
                self._finish_empty(lease, meta.status, seqs)
            else:
                lease.release(ctx.r, mode="final")  # the next prepared frame kicks again
            return None
        opts, calib_over = parse_options(ctx.results.read_options(sid, v) or {}, strict=False)
        calib = apply_calibration(ctx.store.calibration(sid), calib_over)
        recon = SessionReconstruction(calib, opts, window_radius_mm(setup[0], calib), live=True)
        geometry = DziGeometry.for_mosaic(calib.px_per_mm, ctx.config.half_extent_mm)
        held = HeldSession(
            sid=sid,
            version=v,
            lease=lease,
            calib=calib,
            options=opts,
            recon=recon,
            geometry=geometry,
            pyramid=TilePyramid(geometry),
            lost=[int(s) for s in state.get("lost", [])],
            rejected=[int(s) for s in state.get("rejected", [])],
        )
        held.last_renew = time.monotonic()
        self._replay(held, int(state.get("cursor", 0)))
        return held

    def _replay(self, held: HeldSession, cursor: int) -> None:
        """Rebuild the reconstruction from frames [0, cursor) in order (deterministic), then the tile pyramid."""
        lost, rejected = set(held.lost), set(held.rejected)
        for seq in range(cursor):
            self._renew_if_due(held)
            if seq in lost:
                self._lose(held, seq, replay=True)
            elif seq in rejected:
                self._reject(held, seq, replay=True)
            else:
                pf = self.ctx.results.read_prepared(held.sid, held.version, seq)
                if pf is None:  # cannot happen unless files were removed: record it as lost
                    self._lose(held, seq, replay=True)
                    held.lost.append(seq)
                else:
                    self._add(held, pf, replay=True)
        held.cursor = cursor
        held.pyramid.update(held.recon.canvas, set(held.recon.canvas.tiles))
        held.touched.clear()
        held.unreported.clear()
        # counters are idempotent per seq: re-record all, in case the previous holder died before counting
        self._record_counters(held, list(range(cursor)))
        log.info("session taken over at cursor %d (token %d)", cursor, held.lease.token, extra={"session": held.sid})

    # ----- one pass --------------------------------------------------------------------------------------------
    def _run(self, held: HeldSession) -> None:
        key = (held.sid, held.version)
        try:
            self._renew_if_due(held, force=True)
            self._pass(held)
            now = time.monotonic()
            if held.done:
                self._drop(key, release=True)
                return
            if held.dirty and now - held.last_flush >= held.flush_interval:
                self._flush(held, final=False)
            if now - held.last_progress > self.ctx.config.linger_s:
                if held.dirty:
                    self._flush(held, final=False)
                if held.lease.release(self.ctx.r) != 0:
                    self.held.pop(key, None)
        except LeaseLostError:
            log.warning("lease lost; dropping the session's in-memory state", extra={"session": held.sid})
            self.held.pop(key, None)
        except SessionNotFoundError:
            self._drop(key, release=True)
        except Exception as exc:
            self._fault(key, held, exc)

    def _fault(self, key: tuple[str, int], held: HeldSession, exc: Exception) -> None:
        """Drop a session after a fault; hand the lease off after a delay, or let it expire if Redis is down."""
        self.faulted = True
        self.held.pop(key, None)
        if is_transient(exc):
            log.warning("infrastructure fault (%s); session handed off", describe(exc), extra={"session": held.sid})
        else:
            log.error("serving a session failed; handed off", exc_info=exc, extra={"session": held.sid})
        delay = min(self.ctx.config.fault_backoff_max_s, max(1.0, self.ctx.config.fault_backoff_first_s * 10))
        # with Redis down the lease simply expires; the watchdog kick (or the reconciler) wakes a new holder
        with contextlib.suppress(redis.RedisError, OSError):
            held.lease.release(self.ctx.r, mode="handoff", handoff_delay_s=delay)

    def _drop(self, key: tuple[str, int], release: bool) -> None:
        held = self.held.pop(key, None)
        if held is not None and release:
            held.lease.release(self.ctx.r, mode="final")

    def _renew_if_due(self, held: HeldSession, force: bool = False) -> None:
        cfg = self.ctx.config
        now = time.monotonic()
        if not force and now - held.last_renew < cfg.lease_ms / 3000.0:
            return
        if force and now - held.last_renew < cfg.lease_ms / 6000.0:
            return
        watchdog = time.time() + 2.0 * cfg.lease_ms / 1000.0
        if not held.lease.renew(self.ctx.r, cfg.lease_ms, watchdog):
            raise LeaseLostError
        held.last_renew = now

    def _pass(self, held: HeldSession) -> None:
        """Register frames from the cursor while they are available; finish the session when it is complete."""
        ctx, cfg = self.ctx, self.ctx.config
        sid, v = held.sid, held.version
        meta = ctx.store.get_meta(sid)
        finished = meta.finished_at is not None
        started = time.monotonic()
        seqs: list[int] | None = None
        while not ctx.stop.is_set() and time.monotonic() - started < cfg.pass_budget_s:
            seq = held.cursor
            if ctx.results.is_poison(sid, v, seq):
                self._reject(held, seq)
                held.rejected.append(seq)
                self._advance(held)
                continue
            pf = ctx.results.read_prepared(sid, v, seq)
            if pf is not None:
                try:
                    self._add(held, pf)
                except Exception as exc:
                    self._registration_failed(held, seq, exc)
                    raise LeaseLostError from exc
                self._advance(held)
                if time.monotonic() - held.last_flush >= held.flush_interval:
                    self._flush(held, final=False)
                self._renew_if_due(held)
                continue
            rec = ctx.store.get_frame(sid, seq)
            if rec is not None:  # stored, not prepared yet: wait; re-queue if its job seems to have vanished
                if time.time() - rec.received_at > cfg.lost_timeout_s:
                    every_ms = int(1000 * max(cfg.lost_timeout_s, 5.0))  # idempotent, so a duplicate costs little
                    queue.requeue_frame(ctx.r, sid, seq, ctx.prefix, at_most_every_ms=every_ms)
                break
            seqs = stored_seqs(ctx, sid) if seqs is None or seqs[-1:] <= [seq] else seqs
            later = [s for s in seqs if s > seq]
            if not later:
                break
            if not finished:
                nxt = ctx.store.get_frame(sid, later[0])
                if nxt is None or time.time() - nxt.received_at <= cfg.lost_timeout_s:
                    break
            self._lose(held, seq)
            held.lost.append(seq)
            self._advance(held)
        if finished and not ctx.stop.is_set():
            seqs = stored_seqs(ctx, sid)
            if not seqs or held.cursor > seqs[-1]:
                self._complete(held, meta.status)

    def _advance(self, held: HeldSession) -> None:
        held.cursor += 1
        held.dirty = True
        held.last_progress = time.monotonic()

    def _log_order(self, held: HeldSession, seq: int, kind: str) -> None:
        if self.ctx.config.debug_order:
            key = queue.debug_order_key(held.sid, held.version, self.ctx.prefix)
            self.ctx.r.rpush(key, f"{held.lease.token}:{seq}:{kind}")

    def _add(self, held: HeldSession, pf: Any, replay: bool = False) -> None:
        self._log_order(held, pf.seq, "add")
        result, touched = held.recon.add(pf)
        if not replay:
            held.touched |= touched
            held.unreported.append(pf.seq)
            if result.moved:
                held.path_reset = True

    def _lose(self, held: HeldSession, seq: int, replay: bool = False) -> None:
        self._log_order(held, seq, "lost")
        held.recon.lose(seq)
        self._remember_time(held, seq)
        if not replay:
            held.unreported.append(seq)

    def _reject(self, held: HeldSession, seq: int, replay: bool = False) -> None:
        self._log_order(held, seq, "rejected")
        held.recon.reject(seq)
        self._remember_time(held, seq)
        if not replay:
            held.unreported.append(seq)

    def _remember_time(self, held: HeldSession, seq: int) -> None:
        rec = self.ctx.store.get_frame(held.sid, seq)
        if rec is not None:
            held.times[seq] = rec.t_s

    def _registration_failed(self, held: HeldSession, seq: int, exc: Exception) -> None:
        """Count a registration failure of `seq`; after max_deliveries mark it poison; retry via a delayed kick."""
        ctx = self.ctx
        log.error("registration failed: %s", type(exc).__name__, exc_info=exc, extra={"session": held.sid, "seq": seq})
        fails = int(ctx.r.hincrby(queue.regfail_key(held.sid, held.version, ctx.prefix), str(seq), 1))
        if fails >= ctx.config.max_deliveries:
            ctx.results.mark_poison(held.sid, held.version, seq, f"registration failed: {type(exc).__name__}")
            ctx.r.xadd(
                queue.dead_stream(ctx.prefix),
                {
                    "kind": "register-frame",
                    "session": held.sid,
                    "version": str(held.version),
                    "seq": str(seq),
                    "error": f"{type(exc).__name__}: {exc}"[:200],
                },
            )
            queue.incr_metric(ctx.r, "dead_letters_total", prefix=ctx.prefix)
        self.held.pop((held.sid, held.version), None)
        held.lease.release(ctx.r, mode="handoff", handoff_delay_s=0.5)  # a fresh holder retries

    # ----- publishing ------------------------------------------------------------------------------------------
    def _rows(self, held: HeldSession) -> list[PathRow]:
        rows = held.recon.path_rows()
        return [
            replace(r, t_s=held.times[r.seq]) if not math.isfinite(r.t_s) and r.seq in held.times else r for r in rows
        ]

    def _check_fence(self, held: HeldSession) -> None:
        state = self.ctx.results.read_state(held.sid, held.version) or {}
        if int(state.get("fence", 0)) > held.lease.token or not held.lease.held(self.ctx.r):
            raise LeaseLostError

    def _flush(self, held: HeldSession, final: bool) -> None:
        """Write path, changed tiles, images when due, mosaic.json and state; count frames; publish an event."""
        ctx, cfg, pub = self.ctx, self.ctx.config, self.publisher
        sid, v = held.sid, held.version
        self._renew_if_due(held, force=True)
        self._check_fence(held)
        now = time.monotonic()
        rows = self._rows(held)
        pub.write_path(sid, v, rows)
        doc = ctx.results.read_mosaic_meta(sid, v) or {}
        version = int(doc.get("version", 0)) + 1
        revisions: dict[str, dict[str, int]] = doc.get("revisions") or empty_revisions()
        images_due = final or not doc.get("width") or now - held.last_image >= cfg.image_every_s
        held.deferred |= held.pyramid.update(held.recon.canvas, held.touched)
        held.touched = set()
        # levels where one tile holds the whole canvas are only seen zoomed far out: refresh them with the images
        small = held.geometry.tiles_at(0) == (1, 1)
        whole = {k for k in held.deferred if held.geometry.tiles_at(k[0]) == (1, 1)} if small else set()
        changed = held.deferred if images_due else held.deferred - whole
        held.deferred = set() if images_due else whole
        tiles_event = pub.write_tiles(sid, v, held.pyramid, changed, version, revisions, durable=final)
        image = image_meta(doc, held.calib.px_per_mm)
        if images_due:
            image = pub.write_images(sid, v, held.recon.canvas.render(), raw_layers=final)  # + coverage, layers
            held.last_image = now
        finished = ctx.store.get_meta(sid).finished_at is not None
        status = "done" if final else ("processing" if finished else "receiving")
        doc = pub.write_mosaic_json(
            sid,
            v,
            image,
            version=version,
            revisions=revisions,
            geometry=held.geometry,
            extent_mm=canvas_extent_mm(held.recon.canvas),
            rows=rows,
            status=status,
            method=held.options.name,
            compliance=held.recon.compliance if final else None,
            tissue=held.recon.learned_model(),
        )
        pub.write_state(
            sid, v, cursor=held.cursor, fence=held.lease.token, finished=final, lost=held.lost, rejected=held.rejected
        )
        self._record_counters(held, held.unreported)
        pub.results_event(sid, doc, tiles_event, rows, held.unreported, held.path_reset or final)
        held.unreported = []
        held.path_reset = False
        held.dirty = False
        held.last_flush = time.monotonic()
        held.flush_interval = max(cfg.flush_every_s, 2.0 * (held.last_flush - now))

    def _record_counters(self, held: HeldSession, seqs: list[int]) -> None:
        """Count the frames `seqs` that have a registration result (idempotent per seq)."""
        statuses = {s: r.status for s, r in held.recon.results.items()}
        outcomes = [(seq, statuses[seq] != STATUS_OK) for seq in sorted(set(seqs)) if seq in statuses]
        self.publisher.count_frames(held.sid, held.version, outcomes)

    def _complete(self, held: HeldSession, session_status: str) -> None:
        """Final refinement and compliance fit, final flush and render, status done."""
        self._renew_if_due(held, force=True)
        self._check_fence(held)
        held.touched |= held.recon.finish()
        self._flush(held, final=True)
        if held.version == LIVE_VERSION and session_status != "failed":
            self.ctx.store.set_status(held.sid, "done")
        held.done = True
        log.info("session done", extra={"session": held.sid, "frames": len(held.recon.results)})

    def _finish_empty(self, lease: Lease, session_status: str, rejected: list[int] | None = None) -> None:
        """A finished session with no usable frame (none, or all poison): rows rejected, no mosaic, status done."""
        ctx, sid, v = self.ctx, lease.session_id, lease.version
        rejected = sorted(rejected or [])
        opts, calib_over = parse_options(ctx.results.read_options(sid, v) or {}, strict=False)
        calib = apply_calibration(ctx.store.calibration(sid), calib_over)
        geometry = DziGeometry.for_mosaic(calib.px_per_mm, ctx.config.half_extent_mm)
        rows = []
        for seq in rejected:
            rec = ctx.store.get_frame(sid, seq)
            rows.append(rejected_row(seq, rec.t_s if rec is not None else math.nan))
        pub = self.publisher
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
            method=opts.name,
        )
        cursor = rejected[-1] + 1 if rejected else 0
        pub.write_state(sid, v, cursor=cursor, fence=lease.token, finished=True, rejected=rejected)
        pub.count_frames(sid, v, [(seq, True) for seq in rejected])
        if session_status != "failed":
            ctx.store.set_status(sid, "done")
        pub.results_event(sid, doc, {}, rows, rejected, path_reset=True)
        lease.release(ctx.r, mode="final")
