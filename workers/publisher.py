"""The one publisher of results and events: every write of a results version and every session event.

The live register stage and the reprocess stage decide WHAT to publish (which tiles changed, whether the
images are due, the status); this module is the one place that writes it, in the one order readers rely on:
path.json, tiles, images, mosaic.json (services.core.outputs.documents.mosaic_json), state.json; then the frame
counters and the event on the session's stream. Fencing (the lease check before a write) stays with the
register stage, which calls the publisher only while it holds the session.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from services.core.mosaic.canvas import MosaicImage
from services.core.mosaic.deepzoom import TilePyramid
from services.core.outputs.documents import LAYERS, mosaic_json
from services.core.path_rows import PathRow, path_tail
from services.jobs import job_records as jobs
from services.jobs import queue
from services.store.results_store import LIVE_VERSION
from services.store.version_state import VersionState
from workers.config import Context

TileKey = tuple[int, int, int]  # (level, col, row)
Revisions = dict[str, dict[str, int]]  # {layer: {"level/col_row": revision}}


class Publisher:
    """Writes results versions (path, tiles, images, mosaic.json, state), counts frames, publishes events."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx

    # ----- audit -----------------------------------------------------------------------------------------------
    def audit_send(
        self,
        sid: str,
        job_id: str,
        destination: str,
        outcome: str,
        instances: int,
        version: int | None = None,
    ) -> None:
        """Append the audit record of one send attempt: who asked (the job's key), session, destination, outcome."""
        owner = jobs.read_job(self.ctx.r, self.ctx.prefix, job_id).get("owner", "")
        self.ctx.audit.append(
            {
                "ts": round(time.time(), 3),
                "actor": self.ctx.audit.key_actor(owner) if owner else "worker",
                "action": "pacs.send",
                "session": sid,
                "job": job_id,
                "destination": destination,
                "outcome": outcome,
                "instances": int(instances),
                "version": version,
                "worker": self.ctx.config.consumer,
            }
        )

    # ----- results files ---------------------------------------------------------------------------------------
    def write_path(self, sid: str, v: int, rows: Sequence[PathRow]) -> None:
        """Write path.json of version v."""
        self.ctx.results.write_path(sid, v, rows)

    def write_tiles(
        self,
        sid: str,
        v: int,
        pyramid: TilePyramid,
        tiles: Iterable[TileKey],
        revision: int,
        revisions: Revisions,
        *,
        durable: bool = True,
        fresh: bool = False,
        heartbeat: Callable[[], None] = lambda: None,
    ) -> Revisions:
        """Return {layer: {name: revision}} of what changed, rendering and writing `tiles` of both layers.

        A tile with no data any more is deleted (the API serves a blank one) and its revision recorded so that
        clients re-read it; in a `fresh` version (nothing written before) there is nothing to delete or record.
        `revisions` (mosaic.json's) is updated in place. heartbeat is called every 32 tiles: rendering a whole
        pyramid takes seconds on a loaded machine. durable: every tile of the version written so far is on disk when
        this returns (one sync of the filesystem after the writes: a fsync per tile cost 10 ms a tile in a busy
        service). Counts tile_renders_total.
        """
        results = self.ctx.results
        changed: Revisions = {layer: {} for layer in LAYERS}
        keys = sorted(tiles)
        for i, (level, col, row) in enumerate(keys):
            if i % 32 == 31:
                heartbeat()
            name = f"{level}/{col}_{row}"
            for layer in LAYERS:
                png = pyramid.render_png(level, col, row, layer)
                if png is not None:
                    results.write_tile(sid, v, layer, level, col, row, png, durable=False)
                elif fresh:
                    continue
                else:
                    results.delete_tile(sid, v, layer, level, col, row)
                revisions.setdefault(layer, {})[name] = revision
                changed[layer][name] = revision
        if durable:
            results.sync(sid, v)
        if keys:
            queue.incr_metric(self.ctx.r, "tile_renders_total", 2 * len(keys), prefix=self.ctx.prefix)
        return changed

    def write_images(self, sid: str, v: int, mosaic: MosaicImage, raw_layers: bool = True) -> dict[str, Any]:
        """Return the image meta, writing mosaic.png, force.png, coverage.png (and raw_layers: layers.npz)."""
        self.ctx.results.write_mosaic_images(sid, v, mosaic, raw_layers=raw_layers)
        return mosaic.meta()

    def write_tiles_and_images(
        self,
        sid: str,
        v: int,
        pyramid: TilePyramid,
        tiles: Iterable[TileKey],
        revision: int,
        revisions: Revisions,
        render: Callable[[], MosaicImage] | None,
        *,
        raw_layers: bool,
        durable: bool,
        heartbeat: Callable[[], None] = lambda: None,
    ) -> tuple[Revisions, dict[str, Any] | None, tuple[float, float]]:
        """Return what write_tiles returns, the image meta (None without `render`) and the wall and CPU seconds the
        whole images took: the tiles (write_tiles) and, when `render` is given, the mosaic it renders (write_images)
        written at the same time, the images on a thread (rendering, PNG encoding and deflating free the GIL; a
        live session's final flush waits for both)."""
        tiles_args = (sid, v, pyramid, tiles, revision, revisions)
        if render is None:
            return self.write_tiles(*tiles_args, durable=durable, heartbeat=heartbeat), None, (0.0, 0.0)

        def images() -> tuple[dict[str, Any], tuple[float, float]]:
            started, cpu = time.monotonic(), time.thread_time()
            image = self.write_images(sid, v, render(), raw_layers=raw_layers)
            return image, (time.monotonic() - started, time.thread_time() - cpu)

        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="images") as pool:
            pending = pool.submit(images)
            changed = self.write_tiles(*tiles_args, durable=durable, heartbeat=heartbeat)
            image, seconds = pending.result()
        return changed, image, seconds

    def write_mosaic_json(self, sid: str, v: int, image: Mapping[str, Any], **fields: Any) -> dict[str, Any]:
        """Return the mosaic.json of version v, written now: the one shape every producer writes.

        It is documents.mosaic_json(image, results_version=v, **fields) (version, revisions, geometry, extent_mm,
        rows, status, method, compliance, tissue, kinds, units).
        """
        doc = mosaic_json(image, results_version=v, **fields)
        self.ctx.results.write_mosaic_meta(sid, v, doc)
        return doc

    def write_state(self, sid: str, v: int, state: VersionState) -> None:
        """Write state.json of version v (services.store.version_state: the one shape, format-versioned)."""
        self.ctx.results.write_state(sid, v, state)

    # ----- counters and events ---------------------------------------------------------------------------------
    def mark_tracking(self, sid: str, on: bool) -> None:
        """Mark (renewed) or unmark a live session whose next frames are to be prepared to be tracked."""
        queue.set_tracking(self.ctx.r, sid, on, self.ctx.prefix)

    def record_lags(self, sid: str, v: int, lags_s: Sequence[float]) -> None:
        """Record the upload-to-placement lags (s) of frames the live version just published."""
        if v == LIVE_VERSION:
            queue.record_lags(self.ctx.r, sid, lags_s, self.ctx.prefix)

    def count_frames(self, sid: str, v: int, outcomes: Iterable[tuple[int, bool]]) -> None:
        """Count each (seq, lost) of the live version once: session counters, frames_processed/lost_total."""
        if v != LIVE_VERSION:
            return
        ctx = self.ctx
        counted = 0
        lost_counted = 0
        for seq, lost in outcomes:
            if queue.record_frame_result(ctx.r, sid, seq, lost, ctx.prefix):
                counted += 1
                lost_counted += bool(lost)
        if counted:
            queue.incr_metric(ctx.r, "frames_processed_total", counted, prefix=ctx.prefix)
        if lost_counted:
            queue.incr_metric(ctx.r, "frames_lost_total", lost_counted, prefix=ctx.prefix)

    def count_register_cost(self, v: int, frames: Mapping[str, int], cpu_s: Mapping[str, float]) -> None:
        """Add the live version's registered frames and the register stage's CPU seconds on them, by kind
        (SessionReconstruction.frame_kind), to frames_<kind>_total and register_<kind>_cpu_seconds_total."""
        if v != LIVE_VERSION or not frames:
            return
        pipe = self.ctx.r.pipeline(transaction=False)  # one round trip
        for kind, count in frames.items():
            queue.incr_metric(pipe, f"frames_{kind}_total", count, prefix=self.ctx.prefix)
            queue.incr_metric(pipe, f"register_{kind}_cpu_seconds_total", cpu_s[kind], prefix=self.ctx.prefix)
        pipe.execute()

    def count_flush(self, cpu_s: Mapping[str, float]) -> None:
        """Add one flush to flushes_total and its CPU seconds by part (path, pyramid, tiles, images, documents, event:
        workers.stages.register.flush) to flush_<part>_cpu_seconds_total."""
        pipe = self.ctx.r.pipeline(transaction=False)
        queue.incr_metric(pipe, "flushes_total", 1, prefix=self.ctx.prefix)
        for part, seconds in cpu_s.items():
            queue.incr_metric(pipe, f"flush_{part}_cpu_seconds_total", seconds, prefix=self.ctx.prefix)
        pipe.execute()

    def count_finish_ahead(self, cpu_s: float) -> None:
        """Add one finish run ahead and its CPU seconds to finish_ahead_runs_total, finish_ahead_cpu_seconds_total."""
        pipe = self.ctx.r.pipeline(transaction=False)
        queue.incr_metric(pipe, "finish_ahead_runs_total", 1, prefix=self.ctx.prefix)
        queue.incr_metric(pipe, "finish_ahead_cpu_seconds_total", cpu_s, prefix=self.ctx.prefix)
        pipe.execute()

    def count_finish(self, seconds: Mapping[str, float], pasted_again: int) -> None:
        """Add one finished live session to sessions_finished_total, its finish's wall seconds by part (refine,
        calibrate, restitch, final_flush) to finish_<part>_wall_seconds_total and the frames it pasted again to
        finish_frames_pasted_again_total."""
        pipe = self.ctx.r.pipeline(transaction=False)
        queue.incr_metric(pipe, "sessions_finished_total", 1, prefix=self.ctx.prefix)
        queue.incr_metric(pipe, "finish_frames_pasted_again_total", pasted_again, prefix=self.ctx.prefix)
        for part, value in seconds.items():
            queue.incr_metric(pipe, f"finish_{part}_wall_seconds_total", value, prefix=self.ctx.prefix)
        pipe.execute()

    def event(self, sid: str, kind: str, data: dict[str, Any]) -> None:
        """XADD an event {"type", "data": json} to the session's event stream (capped near EVENTS_MAXLEN)."""
        queue.add_event(
            self.ctx.r, sid, kind, json.dumps(data, separators=(",", ":"), allow_nan=False), self.ctx.prefix
        )

    def results_event(
        self,
        sid: str,
        doc: Mapping[str, Any],
        tiles: Revisions,
        rows: Sequence[PathRow],
        reported: Sequence[int],
        path_reset: bool,
    ) -> None:
        """Publish a `progress` (or, status done, `done`) event for the mosaic.json `doc` just written.

        tiles: the changed tiles' revisions; reported: the seqs handled since the last event (the path tail);
        path_reset: an earlier frame moved, clients re-read the whole path.
        """
        status = doc["status"]
        data = {
            "version": doc["results_version"],
            "mosaic_version": doc["version"],
            **doc["frames"],
            "tiles": tiles,
            "path_tail": path_tail(rows, reported),
            "path_reset": bool(path_reset),
            "extent_mm": doc["extent_mm"],
            "status": status,
        }
        self.event(sid, "done" if status == "done" else "progress", data)

    def version_event(self, sid: str, v: int, job_id: str) -> None:
        """Publish a `version` event: reprocess job `job_id` made version v (complete, now current)."""
        meta = self.ctx.results.read_mosaic_meta(sid, v) or {}
        data = {
            "version": v,
            "mosaic_version": meta.get("version", 1),
            "status": "done",
            "job": job_id,
            **meta["frames"],
        }
        self.event(sid, "version", data)
