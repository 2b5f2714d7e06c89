"""GET /metrics: Prometheus exposition of the service's counters and queue gauges (api.metrics writes it).

Counters are read from Redis per scrape, so one scrape of any API process sees the whole deployment; no label
carries a session id or anything about patients. Unauthenticated, like /healthz: it holds counts only.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Response
from fastapi.concurrency import run_in_threadpool

from api.deps import AppSettings, RedisClient
from api.metrics import render_metrics

router = APIRouter(tags=["health"])

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"  # what a scrape without an OpenMetrics Accept gets


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE: {}, "application/openmetrics-text": {}}}},
)
async def metrics(
    r: RedisClient, settings: AppSettings, accept: Annotated[str | None, Header(include_in_schema=False)] = None
) -> Response:
    """Return the Prometheus exposition (text format 0.0.4; OpenMetrics if Accept asks for it)."""
    body, content_type = await run_in_threadpool(render_metrics, r, settings.redis_prefix, accept)
    return Response(body, headers={"Content-Type": content_type, "Cache-Control": "no-store"})
