"""Liveness and readiness probes (spec §5)."""

from __future__ import annotations

import shutil
from pathlib import Path

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool

from api.deps import AppSettings, RedisClient, Store
from api.errors import ServiceUnavailable
from api.schemas import Health
from services.jobs.redis_backend import ping

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """Return 200 whenever the process serves requests."""
    return Health(status="ok")


def free_space_ok(path: Path, min_free_mb: int) -> bool:
    """Return True if the volume holding `path` has at least min_free_mb MiB free (False if unreadable)."""
    try:
        return shutil.disk_usage(path).free >= min_free_mb * 1024 * 1024
    except OSError:
        return False


@router.get(
    "/readyz", response_model=Health, responses={503: {"description": "Redis or storage unavailable, or disk low"}}
)
async def readyz(r: RedisClient, store: Store, settings: AppSettings) -> Health:
    """Return 200 when Redis answers PING, storage accepts a durable write and has min_free_mb free; else 503.

    Below the free-space floor a balancer stops sending uploads here before the disk is full (they would be
    503 insufficient_storage); the process itself stays live (/healthz).
    """
    checks = {
        "redis": await run_in_threadpool(ping, r),
        "storage": await run_in_threadpool(store.writable),
        "disk_space": await run_in_threadpool(free_space_ok, store.root, settings.min_free_mb),
    }
    if not all(checks.values()):
        failing = ", ".join(k for k, ok in checks.items() if not ok)
        raise ServiceUnavailable(f"not ready: {failing} unavailable", settings.retry_after_s, code="not_ready")
    return Health(status="ok", checks=checks)
