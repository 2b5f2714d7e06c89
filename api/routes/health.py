"""Liveness and readiness probes (spec §5)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool

from api.deps import AppSettings, RedisClient, Store
from api.errors import ServiceUnavailable
from api.schemas import Health
from services.redis_backend import ping

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """Return 200 whenever the process serves requests."""
    return Health(status="ok")


@router.get("/readyz", response_model=Health, responses={503: {"description": "Redis or storage unavailable"}})
async def readyz(r: RedisClient, store: Store, settings: AppSettings) -> Health:
    """Return 200 when Redis answers PING and storage accepts a durable write, else 503."""
    checks = {"redis": await run_in_threadpool(ping, r), "storage": await run_in_threadpool(store.writable)}
    if not all(checks.values()):
        failing = ", ".join(k for k, ok in checks.items() if not ok)
        raise ServiceUnavailable(f"not ready: {failing} unavailable", settings.retry_after_s, code="not_ready")
    return Health(status="ok", checks=checks)
