"""Which results version a request is served, for every route that reads results (none imports another route).

`?v=<n>` when given (404 if it does not exist), else the newest version up to the current one that has a
mosaic.json — so while a reprocess runs (its version is current but still empty) the previous results stay
visible. Every answer carries X-Results-Version.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Query, Request

from api.errors import NotFound
from services.core.outputs.documents import extent_view
from services.store.results_store import ResultsStore

VersionQuery = Annotated[int | None, Query(alias="v", ge=1, le=1_000_000, description="results version")]
NOT_READY = "no mosaic yet: no frame of this session has been processed"


def get_results(request: Request) -> ResultsStore:
    """Return the application's ResultsStore (made on first use, over the settings' data_dir)."""
    rs = getattr(request.app.state, "results", None)
    if rs is None:
        rs = ResultsStore(request.app.state.settings.data_dir)
        request.app.state.results = rs
    return rs


async def results_dependency(request: Request) -> ResultsStore:
    """Return get_results(request) without a thread-pool hop (FastAPI runs a plain `def` dependency in one)."""
    return get_results(request)


Results = Annotated[ResultsStore, Depends(results_dependency)]


def resolve_version(rs: ResultsStore, sid: str, requested: int | None) -> int | None:
    """Return the results version to serve (see the module docstring), or None before any exists."""
    if requested is not None:
        if not rs.version_dir(sid, requested).is_dir():
            raise NotFound(f"no results version {requested}", code="no_such_version")
        return requested
    current = rs.current_version(sid)
    if current is None:
        return None
    for v in range(current, 0, -1):
        if (rs.version_dir(sid, v) / "mosaic.json").is_file():
            return v
    return current


def served_version(rs: ResultsStore, sid: str, requested: int | None) -> int:
    """Return the results version to serve; 404 not_ready before any exists."""
    v = resolve_version(rs, sid, requested)
    if v is None:
        raise NotFound(NOT_READY, code="not_ready")
    return v


def reprocess_running(rs: ResultsStore, sid: str) -> bool:
    """Return True while a results version newer than the current one is neither finished nor failed."""
    current = rs.current_version(sid)
    if current is None:
        return False
    try:
        newer = [v for v in rs.list_versions(sid) if v > current]
    except FileNotFoundError:
        return False
    return any((state := rs.read_state(sid, v)) is None or not (state.finished or state.failed) for v in newer)


def served_mosaic(rs: ResultsStore, sid: str, requested: int | None) -> tuple[int, dict[str, Any]]:
    """Return (version, mosaic.json + "results_version") or raise 404 when no frame has been processed yet."""
    v = resolve_version(rs, sid, requested)
    doc = rs.shared_mosaic_meta(sid, v) if v is not None else None
    if v is None or doc is None:
        raise NotFound(NOT_READY, code="not_ready")
    return v, {**doc, "results_version": v}


def session_extent(rs: ResultsStore, sid: str) -> dict[str, Any] | None:
    """Return GET /v1/sessions/{id}'s extent of the served version ({x,y}_{min,max}_mm, sizes mm) or None."""
    v = resolve_version(rs, sid, None)
    doc = rs.shared_mosaic_meta(sid, v) if v is not None else None
    view = extent_view((doc or {}).get("extent_mm"))
    return None if view is None else {**view, "results_version": v}
