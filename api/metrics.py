"""Prometheus exposition of the service's counters and queue gauges (GET /metrics), made by prometheus_client.

Counters live in the Redis hash <prefix>metrics (HINCRBY / HINCRBYFLOAT by every API and worker process), so
one scrape of any API process sees the whole deployment. RedisMetrics is a prometheus_client custom collector
over that hash and the queue streams; the library writes the text (format 0.0.4, or OpenMetrics when the
scraper asks for it in Accept). Known fields get a HELP text; any other numeric field is exported as
veinmosaic_<field> (a counter when it ends in _total), so new worker metrics appear without an API change. No
labels carry session ids or anything about patients: the live lag is one summary over the sessions placing
frames (with how many are behind); a session's own lag is in its state, GET /v1/sessions/{id}.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import redis
from prometheus_client.exposition import choose_encoder
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, Metric, SummaryMetricFamily

from services.core.outputs.scan_quality import LAG_WARNING_S, live_lag
from services.jobs import job_lanes, queue

PREFIX = "veinmosaic_"
# Redis hash field -> (help text). Fields ending in _total are counters.
KNOWN_COUNTERS: dict[str, str] = {
    "uploads_total": "Frames accepted by the API (new uploads, duplicates not counted).",
    "tile_hits_total": "Deep Zoom tile requests answered by the API.",
    "frames_processed_total": "Frames handled by the workers (registered, rejected or lost).",
    "frames_lost_total": "Frames the workers could not place (lost).",
    "frames_rejected_total": "Frames the workers rejected (unreadable or dead-lettered).",
    "jobs_done_total": "Reprocess jobs finished.",
    "jobs_failed_total": "Reprocess jobs failed.",
    "tile_renders_total": "Deep Zoom tiles rendered by the workers.",
    "process_restarts_total": "API and worker processes restarted by the `veinmosaic serve` supervisor.",
    "reconciled_frames_total": "Stored frames with no job and no result that the reconciler enqueued again.",
    "reconcile_runs_total": "Runs of the reconciler (at worker start-up, after a Redis restart, periodically).",
    "prepare_cpu_seconds_total": "CPU seconds the workers spent preparing frames (rectification, vein map).",
    "frames_keyframe_total": "Live frames placed by their features (keyframes).",
    "frames_tracked_total": "Live frames placed by tracking on a keyframe, without features (track_overlap).",
    "frames_unplaced_total": "Live frames registration could not place (lost, rejected, or on a fragment).",
    "register_keyframe_cpu_seconds_total": "CPU seconds the workers spent registering and pasting keyframes.",
    "register_tracked_cpu_seconds_total": "CPU seconds the workers spent registering and pasting tracked frames.",
    "register_unplaced_cpu_seconds_total": "CPU seconds the workers spent on frames they could not place.",
    "finish_ahead_runs_total": "Live sessions' finishes run ahead on a copy (finish_ahead_every_s).",
    "finish_ahead_cpu_seconds_total": "CPU seconds the workers spent running finishes ahead (not the re-pastes).",
    "sessions_finished_total": "Live sessions finished by the workers (final refinement, restitch, final flush).",
    "finish_frames_pasted_again_total": "Frames live sessions' finishes pasted again (moved a quarter pixel or more).",
    **{
        f"finish_{part}_wall_seconds_total": f"Wall seconds of live sessions' finishes spent in {what}."
        for part, what in (
            ("refine", "the final refinement"),
            ("calibrate", "the compliance self-calibration"),
            ("restitch", "pasting moved frames again"),
            ("final_flush", "the final flush"),
        )
    },
    "flushes_total": "Flushes of sessions by the workers (path, tiles, mosaic.json; the whole images when due).",
    **{
        f"flush_{part}_cpu_seconds_total": f"CPU seconds the workers spent in flushes' {what}."
        for part, what in (
            ("path", "path rows and path.json"),
            ("pyramid", "pyramid updates"),
            ("tiles", "tile renders and writes"),
            ("images", "whole images (mosaic.png, force.png, coverage.png)"),
            ("documents", "mosaic.json and state.json"),
            ("event", "counters, lags and events"),
        )
    },
}
SUMMARIES = {"job_seconds": "Wall time of finished reprocess jobs, seconds."}
LIVE_WINDOW_S = 60.0  # a session is live for the lag gauges while frames of it were placed this recently
_NAME_OK = re.compile(r"^[a-zA-Z_][a-zA-Z0-9_]*$")


def _stream_len(r: redis.Redis, key: str) -> int:
    try:
        return int(r.xlen(key))
    except redis.ResponseError:  # the key exists with another type: report nothing rather than fail
        return 0


def _counter(field: str, help_text: str, value: float) -> CounterMetricFamily:
    # prometheus_client names a counter family without _total and writes its sample as <name>_total
    return CounterMetricFamily(PREFIX + field.removesuffix("_total"), help_text, value=value)


class RedisMetrics:
    """A prometheus_client collector: the metrics hash, queue gauges and redis_up, read from Redis per scrape."""

    def __init__(self, r: redis.Redis, prefix: str) -> None:
        self.r, self.prefix = r, prefix

    def live_lag(self) -> tuple[list[float], int, int]:
        """Return (the newest lags (s) of every session placing frames in the last minute, sessions placing, of them
        behind by more than LAG_WARNING_S at p95); empty when Redis is down."""
        try:
            lags, behind = [], 0
            sessions = queue.placing_sessions(self.r, LIVE_WINDOW_S, self.prefix)
            for sid in sessions:
                own = queue.recent_lags(self.r, sid, self.prefix)
                summary = live_lag(own)
                behind += int(summary is not None and summary.p95_s > LAG_WARNING_S)
                lags.extend(own)
            return lags, len(sessions), behind
        except (redis.RedisError, OSError):
            return [], 0, 0

    def read(self) -> tuple[dict[str, float], dict[str, float], float, float, float]:
        """Return (hash fields, stream depths, delayed jobs, dead letters, redis_up); zeros when Redis is down."""
        r, prefix = self.r, self.prefix
        try:
            values: dict[str, float] = {}
            for k, v in r.hgetall(queue.metrics_key(prefix)).items():
                key = k.decode() if isinstance(k, bytes) else str(k)
                try:
                    values[key] = float(v)
                except (TypeError, ValueError):
                    continue
            gauges = {
                "frames": float(queue.queue_depth(r, prefix=prefix)),
                "register": float(_stream_len(r, queue.register_stream(prefix))),
                "jobs": float(job_lanes.depth(r, prefix)),  # on the stream and waiting in the keys' lanes
            }
            delayed_key = queue.delayed_key(prefix)
            delayed = float(r.zcard(delayed_key)) if r.type(delayed_key) in (b"zset", "zset") else 0.0
            return values, gauges, delayed, float(_stream_len(r, queue.dead_stream(prefix))), 1.0
        except (redis.RedisError, OSError):
            return {}, {}, 0.0, 0.0, 0.0

    def collect(self) -> Iterator[Metric]:
        """Yield every metric family of one scrape."""
        values, gauges, delayed, dead, up = self.read()
        for field, help_text in KNOWN_COUNTERS.items():
            yield _counter(field, help_text, values.get(field, 0.0))
        for base, help_text in SUMMARIES.items():
            yield SummaryMetricFamily(
                PREFIX + base,
                help_text,
                count_value=values.get(f"{base}_count", 0.0),
                sum_value=values.get(f"{base}_sum", 0.0),
            )
        known = set(KNOWN_COUNTERS) | {f"{b}_{s}" for b in SUMMARIES for s in ("sum", "count")}
        for field in sorted(set(values) - known):
            if not _NAME_OK.match(field):
                continue
            if field.endswith("_total"):
                yield _counter(field, f"Worker metric {field}.", values[field])
            else:
                yield GaugeMetricFamily(PREFIX + field, f"Worker metric {field}.", value=values[field])
        depth = GaugeMetricFamily(
            PREFIX + "queue_depth", "Jobs waiting or in progress per stream (the queue lag).", labels=["stream"]
        )
        for name, value in gauges.items():
            depth.add_metric([name], value)
        yield depth
        yield GaugeMetricFamily(PREFIX + "delayed_jobs", "Jobs re-scheduled for later (not ready yet).", value=delayed)
        yield GaugeMetricFamily(PREFIX + "dead_letters", "Entries in the dead-letter stream.", value=dead)
        yield GaugeMetricFamily(PREFIX + "redis_up", "1 if Redis answered this scrape, else 0.", value=up)
        lags, placing, behind = self.live_lag()
        lag = GaugeMetricFamily(
            PREFIX + "live_lag_seconds",
            "Upload-to-placement lag of the newest frames of the sessions placing frames in the last minute.",
            labels=["quantile"],
        )
        summary = live_lag(lags)
        if summary is not None:
            lag.add_metric(["0.5"], summary.p50_s)
            lag.add_metric(["0.95"], summary.p95_s)
        yield lag
        yield GaugeMetricFamily(PREFIX + "live_sessions", "Sessions with frames placed in the last minute.", placing)
        yield GaugeMetricFamily(
            PREFIX + "live_sessions_behind",
            f"Of those, sessions whose placements trail their uploads by more than {LAG_WARNING_S:.0f} s (p95).",
            behind,
        )


def render_metrics(r: redis.Redis, prefix: str, accept: str | None = None) -> tuple[bytes, str]:
    """Return (exposition, content type): format 0.0.4, or OpenMetrics when `accept` asks for it."""
    encoder, content_type = choose_encoder(accept or "")
    return encoder(RedisMetrics(r, prefix)), content_type
