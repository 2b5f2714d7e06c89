"""GET /v1/sessions/{id}/events: Server-Sent Events of a session's progress, read from a Redis stream.

The workers XADD {"type": "progress"|"done", "data": <json>} to <prefix>events:<sid>; stream entry ids are
the SSE ids, so a client that reconnects with Last-Event-ID (the header EventSource sends, or
?last_event_id=) gets exactly the entries after it. A fresh connection (or one whose Last-Event-ID was
trimmed away) first gets a "snapshot" event: the current mosaic.json, the whole path and the counters,
with the id of the newest entry at that moment. The stream ends after a "done" entry, or at once (after the
snapshot) when the session is already done or failed. sse-starlette writes the framing (id/event/data lines,
retry, the keep-alive comment every KEEPALIVE_S) and ends the generator when the client goes away. Reads use
redis.asyncio with BLOCK, so no thread and no event-loop time is held while waiting.

Each open stream holds a Redis connection, so they are capped per API process (api.limits.StreamSlots): at
most `events_max_per_principal` per caller (a key, or the viewer links of one session; 429 beyond) and
`events_max_total` in all (503 beyond), both with Retry-After. The slot is freed when the stream ends or the
client goes away. The stream is "private, no-store": it carries the path.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any

import anyio
import redis
import redis.asyncio as aioredis
from fastapi import APIRouter, Header, Query, Request
from fastapi.concurrency import run_in_threadpool
from sse_starlette import EventSourceResponse, ServerSentEvent
from starlette.types import Receive, Scope, Send

from api.caching import PRIVATE_NO_STORE
from api.deps import AppSettings, RedisClient, Store, ViewPrincipal, ViewSession
from api.errors import ServiceUnavailable
from api.limits import principal_key
from api.results_access import Results, resolve_version
from services.core.path_rows import path_rows_from_json, path_tail
from services.jobs import queue
from services.jobs.redis_backend import read_embedded_url
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore

router = APIRouter(prefix="/v1/sessions", tags=["results"])
log = logging.getLogger("veinmosaic.api")

KEEPALIVE_S = 15.0  # a keep-alive comment this often (and the session's status checked when idle this long)
RETRY_MS = 3000  # the reconnection delay suggested to EventSource
SEP = "\n"  # line separator of the framing (the SSE spec allows \n, \r\n or \r)
BATCH = 200  # stream entries read per XREAD
FINAL_STATUSES = ("done", "failed")
_STREAM_ID = re.compile(r"^\d{1,20}(-\d{1,20})?$")


def _id_tuple(stream_id: str) -> tuple[int, int]:
    ms, _, seq = stream_id.partition("-")
    return int(ms), int(seq or 0)


def sse(event: str, data: str, event_id: str | None = None) -> ServerSentEvent:
    """Return one SSE message (sse-starlette splits multi-line data into data: lines)."""
    return ServerSentEvent(data, event=event, id=event_id, sep=SEP)


def keepalive() -> ServerSentEvent:
    """Return the keep-alive comment sse-starlette sends on an idle connection."""
    return ServerSentEvent(comment="keep-alive", sep=SEP)


def snapshot(store: SessionStore, rs: ResultsStore, r: redis.Redis, sid: str, prefix: str) -> dict[str, Any]:
    """Return the snapshot event's data: status, counters, mosaic.json (or null) and the path [[seq, x, y, st]]."""
    meta = store.get_meta(sid)
    v = resolve_version(rs, sid, None)
    mosaic = rs.read_mosaic_meta(sid, v) if v is not None else None
    rows = path_rows_from_json((rs.read_path(sid, v) if v is not None else None) or [])
    counters = queue.session_counters(r, sid, prefix=prefix)
    return {
        "session": sid,
        "status": meta.status,
        "results_version": v,
        "mosaic": None if mosaic is None else {**mosaic, "results_version": v},
        "path": path_tail(rows, (row.seq for row in rows)),  # the progress events' path_tail shape, every row
        "frames_received": store.count_frames(sid),
        "frames_processed": counters["processed"],
        "frames_lost": counters["lost"],
    }


class CountedEventSource(EventSourceResponse):
    """An EventSourceResponse that frees its stream slot when it ends, however it ends."""

    def __init__(self, *args: Any, release: Callable[[], None], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._release = release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Return once the stream has ended (done, client gone or server stopping); the slot is freed then."""
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._release()


def async_redis_url(settings: Any) -> str:
    """Return the URL of the Redis server the app uses (REDIS_URL, else the embedded server's socket)."""
    url = settings.redis_url or read_embedded_url(settings.data_dir)
    if not url:
        raise ServiceUnavailable("the event stream is unavailable; retry later", settings.retry_after_s)
    return url


@router.get(
    "/{session_id}/events",
    response_class=EventSourceResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "snapshot, progress..., done"}},
)
async def events(
    meta: ViewSession,
    principal: ViewPrincipal,
    request: Request,
    store: Store,
    rs: Results,
    r: RedisClient,
    settings: AppSettings,
    last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None,
    last_event_id_q: Annotated[str | None, Query(alias="last_event_id", max_length=41)] = None,
) -> EventSourceResponse:
    """Return the session's progress as an SSE stream: snapshot, then progress events, then done (see module doc)."""
    sid, prefix = meta.id, settings.redis_prefix
    resume = last_event_id or last_event_id_q
    resume = resume.strip() if resume and _STREAM_ID.match(resume.strip()) else None
    url = async_redis_url(settings)
    stream = queue.events_stream(sid, prefix)

    async def generate() -> AsyncIterator[ServerSentEvent]:
        client = aioredis.Redis.from_url(
            url, decode_responses=True, socket_connect_timeout=2.0, socket_timeout=KEEPALIVE_S + 10.0
        )
        try:
            yield ServerSentEvent(retry=RETRY_MS, sep=SEP)
            start = resume
            if start is not None:
                first = await client.xrange(stream, count=1)
                if first and _id_tuple(first[0][0]) > _id_tuple(start) and start != "0-0":
                    start = None  # entries after Last-Event-ID were trimmed: start over with a snapshot
            if start is None:
                newest = await client.xrevrange(stream, count=1)
                start = newest[0][0] if newest else "0-0"
                doc = await run_in_threadpool(snapshot, store, rs, r, sid, prefix)
                yield sse("snapshot", json.dumps(doc, separators=(",", ":"), allow_nan=False), start)
                if newest and newest[0][1].get("type") == "done":  # the run is over: nothing more will come
                    yield sse("done", newest[0][1].get("data", "{}"), start)
                    return
            idle_checked = False
            while True:
                block = None if not idle_checked else int(KEEPALIVE_S * 1000)
                got = await client.xread({stream: start}, count=BATCH, block=block)
                entries = got[0][1] if got else []
                for entry_id, fields in entries:
                    start = entry_id
                    kind = fields.get("type", "progress")
                    yield sse(kind, fields.get("data", "{}"), entry_id)
                    if kind == "done":
                        return
                if entries:
                    continue
                # nothing new: if the session is already over, say so and end; else wait (keep-alive)
                status = (await run_in_threadpool(store.get_meta, sid)).status
                if status in FINAL_STATUSES:
                    yield sse("done", json.dumps({"status": status, "session": sid}), start)
                    return
                idle_checked = True
        except (redis.RedisError, OSError):
            log.warning("event stream interrupted", extra={"session": sid})
            yield ServerSentEvent(comment="interrupted, reconnect", sep=SEP)
        finally:
            with anyio.CancelScope(shield=True):  # a client that went away cancels us: still close the connection
                await client.aclose()

    slots = request.app.state.stream_slots  # 429 over the caller's cap, 503 over the total (api.limits)
    release = slots.acquire(
        principal_key(principal), settings.events_max_per_principal, settings.events_max_total, settings.retry_after_s
    )
    return CountedEventSource(
        generate(),
        release=release,
        headers={"Cache-Control": PRIVATE_NO_STORE},
        ping=KEEPALIVE_S,
        sep=SEP,
        ping_message_factory=keepalive,
    )
