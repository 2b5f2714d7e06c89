"""GET /v1/sessions/{id}/events: Server-Sent Events of a session's progress, read from a Redis stream.

The workers XADD {"type": "progress"|"done", "data": <json>} to <prefix>events:<sid>; stream entry ids are
the SSE ids, so a client that reconnects with Last-Event-ID (the header EventSource sends, or
?last_event_id=) gets exactly the entries after it. A fresh connection (or one whose Last-Event-ID was
trimmed away) first gets a "snapshot" event: the current mosaic.json, the whole path and the counters,
with the id of the newest entry at that moment. The stream ends after a "done" entry, or at once (after the
snapshot) when the session is already done or failed. sse-starlette writes the framing (id/event/data lines,
retry, the keep-alive comment every KEEPALIVE_S) and ends the generator when the client goes away. The
streams share Redis connections (api.event_hub): one reader per API process XREADs (BLOCK) every subscribed
session's stream and fans the entries out, and a small pool serves the snapshot's and the catch-up's short
reads, so no thread, no event-loop time and no connection of its own is held by a waiting stream.

Open streams are still capped per API process (api.limits.StreamSlots: each holds a queue and a response): at
most `events_max_per_principal` per caller (a key, or the viewer links of one session; 429 beyond) and
`events_max_total` in all (503 beyond), both with Retry-After. The slot is freed when the stream ends or the
client goes away. The stream is "private, no-store": it carries the path.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any

import redis
from fastapi import APIRouter, Header, Query, Request
from fastapi.concurrency import run_in_threadpool
from sse_starlette import EventSourceResponse, ServerSentEvent
from starlette.types import Receive, Scope, Send

from api.caching import PRIVATE_NO_STORE
from api.deps import AppSettings, RedisClient, Store, ViewPrincipal, ViewSession
from api.errors import ServiceUnavailable
from api.event_hub import EventHub, id_tuple
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
FINAL_STATUSES = ("done", "failed")
_STREAM_ID = re.compile(r"^\d{1,20}(-\d{1,20})?$")


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


def event_hub(request: Request, url: str) -> EventHub:
    """Return the app's event hub (one Redis reader for all its streams), made on the first stream."""
    hub: EventHub | None = getattr(request.app.state, "event_hub", None)
    if hub is None or hub.url != url:  # a restarted embedded Redis listens on a new socket
        if hub is not None:  # the old one's connections closed, its streams interrupted (they reconnect)
            asyncio.get_running_loop().create_task(hub.close())
        hub = request.app.state.event_hub = EventHub(url)
    return hub


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

    hub = event_hub(request, url)

    async def generate() -> AsyncIterator[ServerSentEvent]:
        sub = None
        try:
            yield ServerSentEvent(retry=RETRY_MS, sep=SEP)
            start = resume
            if start is not None:
                first = await hub.client.xrange(stream, count=1)
                if first and id_tuple(first[0][0]) > id_tuple(start) and start != "0-0":
                    start = None  # entries after Last-Event-ID were trimmed: start over with a snapshot
            if start is None:
                newest = await hub.client.xrevrange(stream, count=1)
                start = newest[0][0] if newest else "0-0"
                doc = await run_in_threadpool(snapshot, store, rs, r, sid, prefix)
                yield sse("snapshot", json.dumps(doc, separators=(",", ":"), allow_nan=False), start)
                if newest and newest[0][1].get("type") == "done":  # the run is over: nothing more will come
                    yield sse("done", newest[0][1].get("data", "{}"), start)
                    return
            sub = hub.subscribe(stream, start)  # first subscribe, then catch up: nothing falls between
            while entries := await hub.catch_up(sub):
                for entry_id, fields in entries:
                    sub.last = entry_id
                    yield sse(fields.get("type", "progress"), fields.get("data", "{}"), entry_id)
                    if fields.get("type") == "done":
                        return
            check = True  # the first time nothing is queued, and after each idle KEEPALIVE_S: is the session over?
            while True:
                try:
                    entry = sub.queue.get_nowait()
                except asyncio.QueueEmpty:
                    if check:  # nothing new: if the session is already over, say so and end; else wait
                        status = (await run_in_threadpool(store.get_meta, sid)).status
                        if status in FINAL_STATUSES:
                            yield sse("done", json.dumps({"status": status, "session": sid}), sub.last)
                            return
                    try:
                        entry = await asyncio.wait_for(sub.queue.get(), timeout=KEEPALIVE_S)
                    except TimeoutError:
                        check = True
                        continue
                    check = False
                if entry is None:  # the hub lost Redis, or this client fell too far behind: it reconnects
                    yield ServerSentEvent(comment="interrupted, reconnect", sep=SEP)
                    return
                entry_id, fields = entry
                if sub.passed(entry_id):
                    continue
                sub.last = entry_id
                kind = fields.get("type", "progress")
                yield sse(kind, fields.get("data", "{}"), entry_id)
                if kind == "done":
                    return
        except (redis.RedisError, OSError):
            log.warning("event stream interrupted", extra={"session": sid})
            yield ServerSentEvent(comment="interrupted, reconnect", sep=SEP)
        finally:
            if sub is not None:
                hub.unsubscribe(sub)

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
