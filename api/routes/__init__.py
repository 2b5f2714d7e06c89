"""HTTP routers of the v1 API; `ROUTERS` is what api.app includes."""

from api.routes.health import router as health_router
from api.routes.ingest import router as ingest_router
from api.routes.sessions import router as sessions_router

ROUTERS = (health_router, sessions_router, ingest_router)

__all__ = ["ROUTERS", "health_router", "ingest_router", "sessions_router"]
