"""Stage 1: prepare one frame of the live run (version 1) and kick registration.

A frame needs the version's setup (window mask and flat field from the first frames, as the offline
pipeline computes them) and force samples covering its time. When either is missing the job is re-scheduled
with a small delay. Preparing twice (a redelivered job) is harmless: the first prepared file stays.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from services.core.physics.force_model import interpolate_forces, samples_around
from services.core.physics.tissue_model import reference_tilts_at
from services.core.pipeline import MASK_SAMPLE_FRAMES, window_setup_of
from services.core.registration.frame_prep import prepare_frame, tracks_when_behind
from services.jobs import queue
from services.store.session_version import SessionVersion
from services.store.storage import SessionMeta, SessionNotFoundError
from workers.config import Context
from workers.retry import Retry
from workers.scan_from_store import stored_forces

log = logging.getLogger("veinmosaic.worker")


DONE = "done"


def ensure_setup(ctx: Context, sv: SessionVersion, meta: SessionMeta) -> tuple[np.ndarray, np.ndarray | None] | None:
    """Return the live version's (mask, flat); compute it once the first frames are in; None if not yet.

    Ready when frames 0..23 are stored, or the session is finished (then the first stored ones), or a frame
    after them arrived more than lost_timeout_s ago (a gap among the first frames will not be filled).
    """
    got = ctx.results.read_setup(sv.sid, sv.v)
    if got is not None:
        return got
    seqs = sv.stored_seqs()
    first = seqs[:MASK_SAMPLE_FRAMES]
    finished = meta.finished_at is not None
    ready = finished or first == list(range(MASK_SAMPLE_FRAMES))
    if not ready and len(seqs) > len([s for s in seqs if s < MASK_SAMPLE_FRAMES]):
        rec = ctx.store.get_frame(sv.sid, min(s for s in seqs if s >= MASK_SAMPLE_FRAMES))
        ready = rec is not None and time.time() - rec.received_at > ctx.config.lost_timeout_s
    if not ready:
        return None
    # bad, undecodable or gone frames are left out; an OSError is raised (the job is retried)
    frames = [img for img in (sv.load_usable(seq) for seq in first) if img is not None]
    if not frames:
        if finished:
            raise ValueError("none of the first frames can be decoded at the calibration's image size")
        return None
    # the offline pipeline's own set-up; a session stored through the API has no mask.png (spec §5 sends none),
    # so the window is found from the frames, as scan_from_store's Scan (mask None) has it when reprocessed
    mask, flat = window_setup_of(frames, None, sv.method_options)
    return ctx.results.write_setup_once(sv.sid, sv.v, mask, flat)


def handle_frame(ctx: Context, sid: str, seq: int) -> str | Retry:
    """Return DONE or a Retry, preparing frame `seq` of session `sid` (live version) and kicking registration."""
    try:
        meta = ctx.store.get_meta(sid)
    except SessionNotFoundError:
        log.warning("frame job for an unknown session dropped", extra={"session": sid})
        return DONE
    sv = ctx.version(sid)
    sv.ensure(ctx.live_options())
    if sv.is_handled(seq):
        queue.mark_frame_handled(ctx.r, sid, seq, ctx.prefix)
        queue.enqueue_register(ctx.r, sid, sv.v, ctx.prefix)
        return DONE
    rec = ctx.store.get_frame(sid, seq)
    if rec is None:
        log.warning("frame job for a frame that is not stored dropped", extra={"session": sid, "seq": seq})
        return DONE
    setup = ensure_setup(ctx, sv, meta)
    if setup is None:
        return Retry(ctx.config.not_ready_delay_s, "setup")
    finished = meta.finished_at is not None
    force_t, forces = ctx.store.merged_forces(sid, covering_t_s=rec.t_s)
    if not finished and (len(force_t) == 0 or force_t[-1] < rec.t_s):
        return Retry(ctx.config.not_ready_delay_s, "forces")
    if finished:
        force_t, forces = stored_forces(ctx.store, sid, rec.t_s)
    forces_n = interpolate_forces(*samples_around(force_t, forces, rec.t_s), np.array([rec.t_s]))[0]
    imu_t, imu = ctx.store.merged_imu(sid, covering_t_s=rec.t_s)  # with the force batches: wait for them too
    if not finished and len(imu_t) and imu_t[-1] < rec.t_s:
        return Retry(ctx.config.not_ready_delay_s, "imu")
    imu_tilt = reference_tilts_at(np.array([rec.t_s]), imu_t, imu)[0]
    # the header must state the calibrated size and a grayscale format before anything is decoded; a frame
    # that does not (BadImageError: its own content, not a fault) is dead-lettered and marked rejected
    calib = sv.calibration
    raw = ctx.store.load_frame(sid, seq, expected_size=calib.image_size)
    mask, flat = setup
    started = time.process_time()
    pf = prepare_frame(
        raw,
        index=seq,
        seq=seq,
        t_s=rec.t_s,
        forces_n=forces_n,
        imu_tilt_deg=imu_tilt,
        calib=calib,
        mask=mask,
        flat=flat,
        options=sv.method_options,
        # its features left to registration, to track it (the mark read only for a method that would)
        behind=tracks_when_behind(sv.method_options) and queue.is_tracking(ctx.r, sid, ctx.prefix),
    )
    cpu_s = time.process_time() - started
    counters = ctx.r.pipeline(transaction=False)  # one round trip
    if ctx.results.write_prepared(sid, sv.v, pf):
        queue.incr_metric(counters, "frames_prepared_total", prefix=ctx.prefix)
    queue.incr_metric(counters, "prepare_cpu_seconds_total", cpu_s, prefix=ctx.prefix)
    counters.execute()
    queue.mark_frame_handled(ctx.r, sid, seq, ctx.prefix)
    queue.enqueue_register(ctx.r, sid, sv.v, ctx.prefix)
    return DONE
