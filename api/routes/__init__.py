"""HTTP routers of the v1 API; `ROUTERS` is what api.app includes."""

from api.routes.events import router as events_router
from api.routes.export import router as export_router
from api.routes.health import router as health_router
from api.routes.ingest import router as ingest_router
from api.routes.metrics import router as metrics_router
from api.routes.openapi import router as openapi_router
from api.routes.report import router as report_router
from api.routes.reprocess import router as reprocess_router
from api.routes.results import router as results_router
from api.routes.send import router as send_router
from api.routes.sessions import router as sessions_router
from api.routes.viewer import router as viewer_router

ROUTERS = (
    health_router,
    metrics_router,
    openapi_router,
    sessions_router,
    ingest_router,
    results_router,
    report_router,
    export_router,
    events_router,
    reprocess_router,
    send_router,
    viewer_router,
)

__all__ = [
    "ROUTERS",
    "events_router",
    "export_router",
    "health_router",
    "ingest_router",
    "metrics_router",
    "openapi_router",
    "report_router",
    "reprocess_router",
    "results_router",
    "send_router",
    "sessions_router",
    "viewer_router",
]
