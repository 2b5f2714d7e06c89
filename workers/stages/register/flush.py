"""Flush timing: what a held session publishes, and when.

A flush writes path.json, the changed tiles, mosaic.json and state.json, counts the frames handled since the
last one and publishes one event, all through the publisher and only after the fence check. Flushes happen at
most every flush_interval (flush_every_s, or twice the last flush's duration if longer: flushing takes at most
a third of the time; behind_flush_every_s while the live session is behind, its newest published frame having
waited more than behind_lag_s since its upload; its next frames are prepared to be tracked while that wait passes
track_lag_s); the whole images (mosaic.png, force.png, coverage.png) at most
every image_every_s and only once the session has caught up with its uploads (a session that is behind spends
the CPU on placing frames), or IMAGES_COST_FACTOR times their last duration if longer (a long examination's mosaic
takes a while to render and encode), and the tiles of levels where one tile holds the whole canvas with them. The final
flush writes the tiles that changed and whatever was deferred, then makes every tile of the version durable.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from services.core.outputs.documents import canvas_extent_mm, empty_revisions, image_meta
from services.core.path_rows import PathRow, with_stored_times
from services.core.registration.outcome import STATUS_OK
from services.store.results_store import LIVE_VERSION
from services.store.version_state import VersionState
from workers.config import Context
from workers.publisher import Publisher
from workers.stages.register.held import HeldSession, RegisterCost
from workers.stages.register.lease import LeaseKeeper

log = logging.getLogger("veinmosaic.worker")
IMAGES_COST_FACTOR = 10.0  # the whole images wait at least this many times their last duration (images_every_s)


def is_behind(caught_up: bool, lags_s: list[float], lag_s: float, held_s: float) -> bool:
    """Return True when a live session is behind its uploads by lag_s: not caught up, even its newest frame just
    published waited more than lag_s since its upload, and this worker has held it for longer than lag_s (held_s:
    before that its frames waited for the session's window set-up, frame 23, or for the worker that held it before,
    not for this one)."""
    return not caught_up and held_s > lag_s and bool(lags_s) and min(lags_s) > lag_s


def tracking_due(caught_up: bool, lags_s: list[float], track_lag_s: float, held_s: float) -> bool:
    """Return True when a live session's next frames are to be prepared to be tracked: it is behind its uploads by
    track_lag_s (is_behind; 0: never)."""
    return track_lag_s > 0 and is_behind(caught_up, lags_s, track_lag_s, held_s)


def flush_every_s(behind: bool, every_s: float, behind_every_s: float) -> float:
    """Return the least time (s) between a session's flushes: every_s, or behind_every_s while the session is
    behind (is_behind: flushing it less often leaves the CPU to placing its frames)."""
    return max(every_s, behind_every_s) if behind else every_s


def images_every_s(every_s: float, last_s: float) -> float:
    """Return the least time (s) between a session's whole images: every_s, or IMAGES_COST_FACTOR times the last
    images' duration (s) if longer, so that a long examination's (its last ones took 0.45 s on a slow day) take at
    most a tenth of its time."""
    return max(every_s, IMAGES_COST_FACTOR * last_s)


def images_due(
    final: bool, written: bool, caught_up: bool, since_s: float, every_s: float, units_changed: bool = False
) -> bool:
    """Return True when a flush writes the whole images: always at the end, the first time or when the canvas's units
    changed since the last ones (a finish run ahead: mosaic.json's px_per_mm and origin_px are theirs), else at most
    every every_s seconds and only once the session has caught up with its uploads."""
    return final or not written or units_changed or (caught_up and since_s >= every_s)


class _Parts:
    """Seconds (wall, and this process's CPU) spent in the named parts of one flush, each lap timed from the
    previous one."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}
        self._last = time.monotonic()
        self._last_cpu = time.process_time()

    def beside(self, lap: str, name: str, seconds: float, cpu_s: float) -> None:
        """Record under `name` a part that ran on another thread during lap `lap`: its wall seconds (overlapping the
        lap's) and its CPU seconds, taken off the lap's."""
        self.seconds[name] = seconds
        self.cpu_s[name] = cpu_s
        self.cpu_s[lap] = max(0.0, self.cpu_s.get(lap, 0.0) - cpu_s)

    def lap(self, name: str) -> None:
        """Record the time since the previous lap under `name`."""
        now, cpu = time.monotonic(), time.process_time()
        self.seconds[name] = round(now - self._last, 3)
        self.cpu_s[name] = cpu - self._last_cpu
        self._last, self._last_cpu = now, cpu


class Flusher:
    """Decides when a held session is flushed and writes the flush through the publisher."""

    def __init__(self, ctx: Context, publisher: Publisher, leases: LeaseKeeper) -> None:
        self.ctx = ctx
        self.publisher = publisher
        self.leases = leases

    def due(self, held: HeldSession, now: float | None = None) -> bool:
        """Return True when flush_interval has passed since the last flush."""
        now = time.monotonic() if now is None else now
        return now - held.clocks.flushed >= held.clocks.flush_interval

    def flush(
        self,
        held: HeldSession,
        final: bool,
        before_event: Callable[[], None] | None = None,
        caught_up: bool = True,
    ) -> dict[str, float]:
        """Return the seconds each part took (path, tiles, images, documents, event), writing path, changed tiles,
        images when due, mosaic.json and state, counting frames and publishing an event.

        caught_up: no registered frame is waiting (False mid-catch-up: the whole images wait for the next flush).
        before_event runs once everything is written and before the event goes out (the completion sets the
        session's status there, so a client woken by the final event reads the status done).
        """
        ctx, cfg, pub = self.ctx, self.ctx.config, self.publisher
        sid, v, pending = held.sid, held.version, held.pending
        self.leases.renew_if_due(held, force=True)
        self.leases.check_fence(held)
        now = time.monotonic()
        parts = _Parts()
        rows = self._rows(held)
        pub.write_path(sid, v, rows)
        parts.lap("path")
        doc = ctx.results.read_mosaic_meta(sid, v) or {}
        version = int(doc.get("version", 0)) + 1
        revisions: dict[str, dict[str, int]] = doc.get("revisions") or empty_revisions()
        every_images = images_every_s(cfg.image_every_s, held.clocks.images_s)
        units = held.recon.canvas.units
        px_per_mm = units.path_px_per_mm(held.calib.px_per_mm)  # the mosaic's, per path mm
        regeared = (doc.get("px_per_mm"), (doc.get("dzi") or {}).get("origin_px")) != (
            px_per_mm,
            held.geometry.to_dict(units)["origin_px"],
        )
        written = bool(doc.get("width"))
        since = now - held.clocks.images
        with_images = images_due(final, written, caught_up, since, every_images, units_changed=written and regeared)
        pending.deferred |= held.pyramid.update(held.recon.canvas, pending.touched)
        pending.touched = set()
        # levels where one tile holds the whole canvas are only seen zoomed far out: refresh them with the images
        small = held.geometry.tiles_at(0) == (1, 1)
        whole = {k for k in pending.deferred if held.geometry.tiles_at(k[0]) == (1, 1)} if small else set()
        changed = pending.deferred if with_images else pending.deferred - whole
        pending.deferred = set() if with_images else whole
        # a flush after a global refinement re-renders much of the pyramid: keep the lease while it does
        renew = lambda: self.leases.renew_if_due(held)  # noqa: E731
        parts.lap("pyramid")
        render = held.recon.canvas.render if with_images else None  # + coverage, layers: beside the tiles
        tiles_event, rendered, (images_s, images_cpu_s) = pub.write_tiles_and_images(
            sid, v, held.pyramid, changed, version, revisions, render, raw_layers=final, durable=final, heartbeat=renew
        )
        parts.lap("tiles")
        image = image_meta(doc, px_per_mm) if rendered is None else rendered
        if with_images:
            parts.beside("tiles", "images", images_s, images_cpu_s)
            held.clocks.images = now
            held.clocks.images_s = images_s
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
            placed=held.recon.placed_counts(),
            units=units,
        )
        fence = held.lease.token
        pub.write_state(sid, v, VersionState(held.cursor, fence, final, lost=held.lost, rejected=held.rejected))
        parts.lap("documents")
        self.record_counters(held, pending.seqs)
        self.publisher.count_register_cost(v, pending.cost.frames, pending.cost.cpu_s)
        pending.cost = RegisterCost()
        lags = self.record_lags(held, pending.seqs)
        held_s = time.time() - held.taken_at
        # the tracking mark settled before the event (and before the completion marks the session done)
        tracking = tracking_due(caught_up, lags, cfg.track_lag_s, held_s)  # its next frames are prepared to be tracked
        if tracking or held.tracking:  # renewed while behind, cleared once
            self.publisher.mark_tracking(held.sid, tracking)
        if before_event is not None:
            before_event()
        pub.results_event(sid, doc, tiles_event, rows, pending.seqs, pending.path_reset or final)
        parts.lap("event")
        self.publisher.count_flush(parts.cpu_s)
        pending.seqs = []
        pending.path_reset = False
        pending.dirty = False
        held.clocks.flushed = time.monotonic()
        held.behind = is_behind(caught_up, lags, cfg.behind_lag_s, held_s)  # its frames' moved neighbours wait (cursor)
        # three probes on two cores: 18.2 -> 24.1 frames/s placed with the behind rule (bench/probes.py)
        every = flush_every_s(held.behind, cfg.flush_every_s, cfg.behind_flush_every_s)
        held.clocks.flush_interval = max(every, 2.0 * (held.clocks.flushed - now))
        if tracking != held.tracking:
            state = "behind its uploads: its next frames are tracked" if tracking else "caught up: frames described"
            waited = min(lags, default=0.0)
            log.info("session %s (newest frame waited %.1f s)", state, waited, extra={"session": held.sid})
        held.tracking = tracking
        return parts.seconds

    def record_lags(self, held: HeldSession, seqs: list[int]) -> list[float]:
        """Return the lags (s) recorded: for each newly published frame, now minus its upload's commit time.

        Only the live version's lags are recorded (else none).
        """
        if held.version != LIVE_VERSION or not seqs:
            return []
        now = time.time()
        records = (self.ctx.store.get_frame(held.sid, seq) for seq in sorted(set(seqs)))
        lags = [now - rec.received_at for rec in records if rec is not None]
        self.publisher.record_lags(held.sid, held.version, lags)
        return lags

    def record_counters(self, held: HeldSession, seqs: list[int]) -> None:
        """Count the frames `seqs` that have a registration result (idempotent per seq)."""
        statuses = {s: r.status for s, r in held.recon.results.items()}
        outcomes = [(seq, statuses[seq] != STATUS_OK) for seq in sorted(set(seqs)) if seq in statuses]
        self.publisher.count_frames(held.sid, held.version, outcomes)

    @staticmethod
    def _rows(held: HeldSession) -> list[PathRow]:
        """Return the path rows, with the stored time of frames registered without a prepared frame."""
        return with_stored_times(held.recon.path_rows(), held.times)
