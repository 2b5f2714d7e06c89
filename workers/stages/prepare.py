"""Stage 1: prepare one frame of the live run (version 1) and kick registration.

A frame needs the version's setup (window mask and flat field from the first frames, as the offline
pipeline computes them) and force samples covering its time. When either is missing the job is re-scheduled
with a small delay. Preparing twice (a redelivered job) is harmless: the first prepared file stays.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass

import numpy as np

from services.core.calibration import Calibration
from services.core.force_model import interpolate_forces
from services.core.frame_prep import prepare_frame
from services.core.image_header import BadImageError
from services.core.method_options import apply_calibration, parse_options
from services.core.methods import MethodOptions
from services.core.pipeline import MASK_SAMPLE_FRAMES, window_setup_of
from services.jobs import queue
from services.store.results_store import LIVE_VERSION
from services.store.storage import SessionMeta, SessionNotFoundError, StorageError
from workers.config import Context
from workers.scan_from_store import stored_forces

log = logging.getLogger("veinmosaic.worker")


@dataclass(frozen=True)
class Retry:
    """The job cannot run yet: put it back after delay_s."""

    delay_s: float
    reason: str


DONE = "done"


def stored_seqs(ctx: Context, sid: str) -> list[int]:
    """Return the seqs of the session's committed frames, ascending (directory names only: cheap)."""
    with os.scandir(ctx.store.frames_dir(sid)) as it:
        names = [e.name for e in it if e.name.endswith(".json") and not e.name.startswith(".")]
    return sorted(int(n[:-5]) for n in names if n[:-5].isdigit())


def live_options(ctx: Context, sid: str) -> tuple[MethodOptions, Calibration]:
    """Return the live version's method options and calibration, creating version 1 on first use."""
    doc = ctx.results.read_options(sid, LIVE_VERSION) if _has_version(ctx, sid, LIVE_VERSION) else None
    if doc is None:
        ctx.results.ensure_version(sid, LIVE_VERSION, {"method": ctx.config.method, "source": "live"})
        doc = ctx.results.read_options(sid, LIVE_VERSION) or {}
    opts, calib = parse_options(doc, strict=False)
    return opts, apply_calibration(ctx.store.calibration(sid), calib)


def _has_version(ctx: Context, sid: str, v: int) -> bool:
    return (ctx.results.version_dir(sid, v) / "options.json").exists()


def _setup_frames(ctx: Context, sid: str, seqs: list[int], calib: Calibration) -> list[np.ndarray]:
    frames = []
    shape = (calib.image_size[1], calib.image_size[0])
    for seq in seqs:
        try:
            img = ctx.store.load_frame(sid, seq, expected_size=calib.image_size)  # header checked before decoding
        except (StorageError, KeyError, BadImageError):  # bad, undecodable or gone; an OSError is raised: retried
            continue
        if img.shape == shape and img.dtype in (np.uint8, np.uint16):
            frames.append(img)
    return frames


def ensure_setup(
    ctx: Context, sid: str, meta: SessionMeta, opts: MethodOptions, calib: Calibration
) -> tuple[np.ndarray, np.ndarray | None] | None:
    """Return the live version's (mask, flat); compute it once the first frames are in; None if not yet.

    Ready when frames 0..23 are stored, or the session is finished (then the first stored ones), or a frame
    after them arrived more than lost_timeout_s ago (a gap among the first frames will not be filled).
    """
    got = ctx.results.read_setup(sid, LIVE_VERSION)
    if got is not None:
        return got
    seqs = stored_seqs(ctx, sid)
    first = seqs[:MASK_SAMPLE_FRAMES]
    finished = meta.finished_at is not None
    ready = finished or first == list(range(MASK_SAMPLE_FRAMES))
    if not ready and len(seqs) > len([s for s in seqs if s < MASK_SAMPLE_FRAMES]):
        later = min(s for s in seqs if s >= MASK_SAMPLE_FRAMES)
        rec = ctx.store.get_frame(sid, later)
        ready = rec is not None and time.time() - rec.received_at > ctx.config.lost_timeout_s
    if not ready:
        return None
    frames = _setup_frames(ctx, sid, first, calib)
    if not frames:
        if finished:
            raise ValueError("none of the first frames can be decoded at the calibration's image size")
        return None
    # the offline pipeline's own set-up; a session stored through the API has no mask.png (spec §5 sends none),
    # so the window is found from the frames, as scan_from_store's Scan (mask None) has it when reprocessed
    mask, flat = window_setup_of(frames, None, opts)
    return ctx.results.write_setup_once(sid, LIVE_VERSION, mask, flat)


def handle_frame(ctx: Context, sid: str, seq: int) -> str | Retry:
    """Prepare frame `seq` of session `sid` (live version) and kick registration; DONE or Retry."""
    try:
        meta = ctx.store.get_meta(sid)
    except SessionNotFoundError:
        log.warning("frame job for an unknown session dropped", extra={"session": sid})
        return DONE
    opts, calib = live_options(ctx, sid)
    v = LIVE_VERSION
    if ctx.results.has_prepared(sid, v, seq) or ctx.results.is_poison(sid, v, seq):
        queue.mark_frame_handled(ctx.r, sid, seq, ctx.prefix)
        queue.enqueue_register(ctx.r, sid, v, ctx.prefix)
        return DONE
    rec = ctx.store.get_frame(sid, seq)
    if rec is None:
        log.warning("frame job for a frame that is not stored dropped", extra={"session": sid, "seq": seq})
        return DONE
    setup = ensure_setup(ctx, sid, meta, opts, calib)
    if setup is None:
        return Retry(ctx.config.not_ready_delay_s, "setup")
    finished = meta.finished_at is not None
    force_t, forces = ctx.store.merged_forces(sid)
    if not finished and (len(force_t) == 0 or force_t[-1] < rec.t_s):
        return Retry(ctx.config.not_ready_delay_s, "forces")
    if finished:
        force_t, forces = stored_forces(ctx.store, sid, rec.t_s)
    forces_n = interpolate_forces(force_t, forces, np.array([rec.t_s]))[0]
    # the header must state the calibrated size and a grayscale format before anything is decoded; a frame
    # that does not (BadImageError: its own content, not a fault) is dead-lettered and marked rejected
    raw = ctx.store.load_frame(sid, seq, expected_size=calib.image_size)
    mask, flat = setup
    pf = prepare_frame(
        raw, index=seq, seq=seq, t_s=rec.t_s, forces_n=forces_n, calib=calib, mask=mask, flat=flat, options=opts
    )
    if ctx.results.write_prepared(sid, v, pf):
        queue.incr_metric(ctx.r, "frames_prepared_total", prefix=ctx.prefix)
    queue.mark_frame_handled(ctx.r, sid, seq, ctx.prefix)
    queue.enqueue_register(ctx.r, sid, v, ctx.prefix)
    return DONE
