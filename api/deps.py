"""FastAPI dependencies as Annotated aliases: settings, store, Redis, principals and visible sessions.

Dependencies that only read app.state (or hash a key) are `async def`: FastAPI runs a plain `def` dependency
in its thread pool, a hop that costs more CPU than the work. Those that touch the disk stay `def`.
"""

from __future__ import annotations

import logging
from typing import Annotated

import redis
from fastapi import Depends, Request

from api.auth import Principal, require_scope, view_principal, visible_session
from api.errors import PayloadTooLarge
from services.jobs import queue
from services.settings import Settings
from services.store.storage import SessionMeta, SessionStore

log = logging.getLogger("veinmosaic.api")


async def get_settings_dep(request: Request) -> Settings:
    """Return the settings read at start-up."""
    return request.app.state.settings


async def get_store(request: Request) -> SessionStore:
    """Return the application's SessionStore."""
    return request.app.state.store


async def get_redis(request: Request) -> redis.Redis:
    """Return the application's Redis client."""
    return request.app.state.redis


async def get_queue_guard(request: Request) -> queue.DepthGuard:
    """Return the application's queue-full check (api.app makes one per app)."""
    return request.app.state.queue_guard


AppSettings = Annotated[Settings, Depends(get_settings_dep)]
Store = Annotated[SessionStore, Depends(get_store)]
RedisClient = Annotated[redis.Redis, Depends(get_redis)]
QueueGuard = Annotated[queue.DepthGuard, Depends(get_queue_guard)]

IngestPrincipal = Annotated[Principal, Depends(require_scope("ingest"))]
AdminPrincipal = Annotated[Principal, Depends(require_scope("admin"))]
ReadPrincipal = Annotated[Principal, Depends(require_scope("ingest", "view"))]
ViewPrincipal = Annotated[Principal, Depends(view_principal)]


def ingest_session(session_id: str, principal: IngestPrincipal, store: Store) -> SessionMeta:
    """Return the metadata of a session the ingest key owns (404 otherwise)."""
    return visible_session(store, principal, session_id)


def view_session(session_id: str, principal: ViewPrincipal, store: Store) -> SessionMeta:
    """Return the meta of a session the caller may view: owner key, admin or viewer token (else 404)."""
    return visible_session(store, principal, session_id)


IngestSession = Annotated[SessionMeta, Depends(ingest_session)]
ViewSession = Annotated[SessionMeta, Depends(view_session)]


def incr(r: redis.Redis, prefix: str, field: str, amount: int = 1) -> None:
    """Add `amount` to counter `field` of the metrics hash; a Redis failure is logged, never raised."""
    try:
        queue.incr_metric(r, field, amount, prefix=prefix)
    except (redis.RedisError, OSError):
        log.warning("metrics counter not updated", extra={"route": field})


async def read_body(request: Request, limit: int) -> bytes:
    """Return the request body; PayloadTooLarge (413, api.errors) as soon as it passes `limit` bytes."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise PayloadTooLarge(f"request body larger than {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)
