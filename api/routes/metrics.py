"""GET /metrics: Prometheus text exposition (format 0.0.4) of the service's counters and queue gauges.

Counters live in the Redis hash <prefix>metrics (HINCRBY / HINCRBYFLOAT by every API and worker process), so
one scrape of any API process sees the whole deployment. Known fields get a HELP text; any other numeric
field is exported as veinmosaic_<field> (a counter when it ends in _total), so new worker metrics appear
without an API change. No labels carry session ids or anything about patients. Unauthenticated, like
/healthz: it holds counts only.
"""

from __future__ import annotations

import logging
import math
import re

import redis
from fastapi import APIRouter, Response
from fastapi.concurrency import run_in_threadpool

from api.deps import AppSettings, RedisClient
from services import queue

router = APIRouter(tags=["health"])
log = logging.getLogger("veinmosaic.api")

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
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
}
SUMMARIES = {"job_seconds": "Wall time of finished reprocess jobs, seconds."}
_NAME_OK = re.compile(r"^[a-zA-Z_][a-zA-Z0-9_]*$")


def _number(value: float) -> str:
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return str(int(value)) if float(value).is_integer() and abs(value) < 2**53 else repr(float(value))


def _family(lines: list[str], name: str, kind: str, help_text: str, samples: list[tuple[str, str, float]]) -> None:
    lines.append(f"# HELP {name} {help_text}")
    lines.append(f"# TYPE {name} {kind}")
    for suffix, labels, value in samples:
        lines.append(f"{name}{suffix}{labels} {_number(value)}")


def _stream_len(r: redis.Redis, key: str) -> int:
    try:
        return int(r.xlen(key))
    except redis.ResponseError:  # the key exists with another type: report nothing rather than fail
        return 0


def render_metrics(r: redis.Redis, prefix: str) -> str:
    """Return the exposition text: counters from the metrics hash, queue gauges, and redis_up (1 or 0)."""
    lines: list[str] = []
    try:
        raw = r.hgetall(queue.metrics_key(prefix))
        values: dict[str, float] = {}
        for k, v in raw.items():
            key = k.decode() if isinstance(k, bytes) else str(k)
            try:
                values[key] = float(v)
            except (TypeError, ValueError):
                continue
        gauges = {
            "frames": float(queue.queue_depth(r, prefix=prefix)),
            "register": float(_stream_len(r, queue.register_stream(prefix))),
            "jobs": float(_stream_len(r, queue.jobs_stream(prefix))),
        }
        delayed_key = queue.delayed_key(prefix)
        delayed = float(r.zcard(delayed_key)) if r.type(delayed_key) in (b"zset", "zset") else 0.0
        dead = float(_stream_len(r, queue.dead_stream(prefix)))
        up = 1.0
    except (redis.RedisError, OSError):
        values, gauges, delayed, dead, up = {}, {}, 0.0, 0.0, 0.0

    for field, help_text in KNOWN_COUNTERS.items():
        _family(lines, PREFIX + field, "counter", help_text, [("", "", values.get(field, 0.0))])
    for base, help_text in SUMMARIES.items():
        samples = [("_sum", "", values.get(f"{base}_sum", 0.0)), ("_count", "", values.get(f"{base}_count", 0.0))]
        _family(lines, PREFIX + base, "summary", help_text, samples)
    known = set(KNOWN_COUNTERS) | {f"{b}_{s}" for b in SUMMARIES for s in ("sum", "count")}
    for field in sorted(set(values) - known):
        if not _NAME_OK.match(field):
            continue
        kind = "counter" if field.endswith("_total") else "gauge"
        _family(lines, PREFIX + field, kind, f"Worker metric {field}.", [("", "", values[field])])
    _family(
        lines,
        PREFIX + "queue_depth",
        "gauge",
        "Jobs waiting or in progress per stream (the queue lag).",
        [("", f'{{stream="{name}"}}', value) for name, value in gauges.items()],
    )
    _family(
        lines, PREFIX + "delayed_jobs", "gauge", "Jobs re-scheduled for later (not ready yet).", [("", "", delayed)]
    )
    _family(lines, PREFIX + "dead_letters", "gauge", "Entries in the dead-letter stream.", [("", "", dead)])
    _family(lines, PREFIX + "redis_up", "gauge", "1 if Redis answered this scrape, else 0.", [("", "", up)])
    return "\n".join(lines) + "\n"


@router.get("/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE: {}}}})
async def metrics(r: RedisClient, settings: AppSettings) -> Response:
    """Return the Prometheus text exposition (format 0.0.4)."""
    text = await run_in_threadpool(render_metrics, r, settings.redis_prefix)
    return Response(text, media_type=CONTENT_TYPE, headers={"Cache-Control": "no-store"})
