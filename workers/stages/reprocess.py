"""Reprocess jobs: a new results version of a session by the OFFLINE pipeline over its stored raw uploads.

The raw uploads are never modified. The new version becomes current only when it is complete, so the API
keeps serving the previous version meanwhile. Progress is in the job hash <prefix>job:<id>.

A reprocess starts from every raw upload, not from the live run's verdicts: a frame the live run rejected
(perhaps for a fault since repaired) is tried again; only frames that cannot be decoded at the calibration's
size now are rejected. An infrastructure fault (full disk, Redis) puts the job back on the queue (the
half-made version is removed); it never fails the job.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable, Mapping
from typing import Any

from services.core.mosaic.canvas import MosaicImage, SparseCanvas
from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
from services.core.outputs.documents import canvas_extent_mm, empty_revisions
from services.core.path_rows import UNCOUNTED, PathRow, PlacedCounts
from services.core.physics.compliance import ComplianceFit
from services.core.pipeline import reconstruct
from services.jobs import queue
from services.store.session_version import method_of
from services.store.storage import SessionNotFoundError
from services.store.stored_report import write_version_report
from services.store.version_state import VersionState
from workers.config import Context
from workers.faults import failure_frames, failure_reason, is_transient
from workers.publisher import Publisher
from workers.scan_from_store import scan_from_store

log = logging.getLogger("veinmosaic.worker")


class JobInterruptedError(Exception):
    """The worker is stopping: the job goes back on the queue."""


def write_report(ctx: Context, sid: str, v: int) -> dict[str, Any] | None:
    """Write version v's report (report.json + plots) against the session's reference; None without one."""
    text = ctx.results.read_reference(sid)
    if text is None:
        return None
    try:
        return write_version_report(ctx.results, sid, v, text, (rec.seq for rec in ctx.store.list_frames(sid)))
    except ValueError as exc:  # NoPathYetError, NothingToCompareError: the version is served without a report
        log.warning("no report for the new version: %s", type(exc).__name__, extra={"session": sid})
        return None


def _fail(ctx: Context, job_id: str, error: str) -> None:
    """Count a reprocess job failed (jobs_failed_total on /metrics), then mark it so with its reason: a client woken by
    its state sees it counted."""
    queue.incr_metric(ctx.r, "jobs_failed_total", prefix=ctx.prefix)
    ctx.update_job(job_id, state="failed", error=error[:300])


def handle_job(ctx: Context, fields: dict[str, str], heartbeat: Callable[[], None]) -> None:
    """Run one reprocess job to completion (job hash state done or failed); JobInterruptedError on stop."""
    job_id, sid = fields.get("job", ""), fields.get("session", "")
    started = time.perf_counter()
    try:
        doc = json.loads(fields.get("options") or "{}")
        opts, calib = method_of(ctx.store, sid, doc)
    except SessionNotFoundError:
        _fail(ctx, job_id, "no such session")
        return
    except ValueError as exc:
        _fail(ctx, job_id, f"invalid options: {exc}")
        return
    v = ctx.results.create_version(sid, {**doc, "source": "reprocess", "job": job_id}, make_current=False)
    sv = ctx.version(sid, v)
    ctx.update_job(job_id, state="running", version=v, started=time.time())
    try:
        heartbeat()
        poison = sv.unusable_seqs()  # decodes every frame the live run did not prepare
        heartbeat()
        scan = scan_from_store(ctx.store, sid, calib, exclude_seqs=poison)
        ctx.update_job(job_id, total=len(scan) + len(poison), done=0)
        last = [0.0]

        def progress(done: int, total: int) -> None:
            if ctx.stop.is_set():
                raise JobInterruptedError
            now = time.monotonic()
            if now - last[0] >= 0.5 or done == total:
                last[0] = now
                ctx.update_job(job_id, done=done)
                heartbeat()

        recon = reconstruct(scan, opts, progress=progress)
        rows = sorted([*recon.rows, *(sv.rejected_row(s) for s in poison)], key=lambda r: r.seq)
        heartbeat()
        write_version(
            ctx,
            sid,
            v,
            rows,
            recon.mosaic,
            recon.method,
            recon.compliance,
            heartbeat,
            recon.learned,
            recon.placed,
        )
        heartbeat()
        write_report(ctx, sid, v)
        ctx.results.set_current(sid, v)
    except JobInterruptedError:
        ctx.update_job(job_id, state="queued", done=0)  # back on the queue; the half-made version is never current
        raise
    except Exception as exc:
        if is_transient(exc):  # the worker re-schedules the job; it starts over in a fresh version
            shutil.rmtree(ctx.results.version_dir(sid, v), ignore_errors=True)
            ctx.update_job(job_id, state="queued", done=0)
            raise
        reason = failure_reason(exc)
        log.error("reprocess job failed: %s\n%s", reason, failure_frames(exc))
        _fail(ctx, job_id, reason)
        Publisher(ctx).write_state(sid, v, VersionState(failed=True))  # the viewer's banner stops
        return
    seconds = time.perf_counter() - started
    queue.incr_metric(ctx.r, "jobs_done_total", prefix=ctx.prefix)  # counted before the state a client waits for
    queue.incr_metric(ctx.r, "job_seconds_sum", seconds + 1e-9, prefix=ctx.prefix)
    queue.incr_metric(ctx.r, "job_seconds_count", prefix=ctx.prefix)
    ctx.update_job(job_id, state="done", done=len(rows), finished=time.time())
    Publisher(ctx).version_event(sid, v, job_id)


def write_version(
    ctx: Context,
    sid: str,
    v: int,
    rows: list[PathRow],
    mosaic: MosaicImage,
    method: str,
    compliance: ComplianceFit | None,
    heartbeat: Callable[[], None] = lambda: None,
    tissue: Mapping[str, Any] | None = None,
    placed: PlacedCounts = UNCOUNTED,
) -> None:
    """Write a complete version: path, all tiles of both layers, mosaic.png/force.png, mosaic.json, state.

    heartbeat is called every 32 tiles: rendering a whole pyramid takes seconds on a loaded machine, longer
    than another worker waits before it claims the job's entry as abandoned (and runs it a second time).
    placed: how many placed frames were tracked without features and how many are pasted into the mosaic
    (mosaic.json's frames: documents.frame_counts).
    """
    pub = Publisher(ctx)
    pub.write_path(sid, v, rows)
    geometry = DziGeometry.for_mosaic(mosaic.px_per_mm, ctx.config.half_extent_mm)
    pyramid = TilePyramid(geometry)
    canvas = SparseCanvas.from_mosaic(mosaic)
    changed = pyramid.update(canvas, set(canvas.tiles))
    revisions = empty_revisions()
    pub.write_tiles(sid, v, pyramid, changed, 1, revisions, fresh=True, heartbeat=heartbeat)
    pub.write_images(sid, v, mosaic)  # mosaic, force, coverage PNGs and the raw layers.npz
    pub.write_mosaic_json(
        sid,
        v,
        mosaic.meta(),
        version=1,
        revisions=revisions,
        geometry=geometry,
        extent_mm=canvas_extent_mm(canvas),
        rows=rows,
        status="done",
        method=method,
        compliance=compliance,
        tissue=tissue,
        placed=placed,
    )
    pub.write_state(sid, v, VersionState(cursor=len(rows), finished=True))
