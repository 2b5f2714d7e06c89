"""Results of a session (spec §4, §5): path, mosaic.json, whole images, Deep Zoom tiles, reference and report.

Which results version is served: `?v=<n>` when given (404 if it does not exist), else the newest version up
to the current one that has a mosaic.json — so while a reprocess runs (its version is current but still
empty) the previous results stay visible. Every answer carries X-Results-Version.

Caching: mosaic.json, the whole images and the DZI descriptor are "no-cache" with an ETag (304 on a
matching If-None-Match). A tile requested with both ?v= and ?rev= is immutable ("private": these are
patient images behind a credential, never for shared caches); without them it is "no-cache". Tile
revisions restart in every results version, hence v in the immutable URL.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from api.deps import AppSettings, IngestSession, RedisClient, Store, ViewSession
from api.errors import Conflict, NotFound, PayloadTooLarge, UnsupportedMediaType, Validation
from api.routes.metrics import incr
from services.plots import figure_bytes, plot_paths_over_mosaic
from services.results_io import path_csv
from services.results_store import ResultsStore, parse_reference_csv
from services.session_reconstruction import PATH_COLUMNS, PathRow
from services.session_report import SessionReport, build_session_report, path_arrays
from services.storage import SessionStore

router = APIRouter(prefix="/v1/sessions", tags=["results"])
log = logging.getLogger("veinmosaic.api")

Layer = Literal["vein", "force"]
ImageLayer = Literal["vein", "force", "coverage"]
LAYER_IMAGES: dict[str, str] = {"vein": "mosaic.png", "force": "force.png", "coverage": "coverage.png"}
PLOT_NAMES = ("paths", "errors")
IMAGE_FILES = ("paths.png", "errors.png")  # the report images stored per version (the sheet is rendered on request)
IMMUTABLE = "private, max-age=31536000, immutable"
NO_CACHE = "no-cache"
REFERENCE_TYPES = {"text/csv", "text/plain", "application/csv", "application/octet-stream", ""}
_FLOAT_COLUMNS = {"t_s", "x_mm", "y_mm", "yaw_deg", "fz_n", "tilt_x_deg", "tilt_y_deg", "stretch"}

VersionQuery = Annotated[int | None, Query(alias="v", ge=1, le=1_000_000, description="results version")]
LayerQuery = Annotated[Layer, Query(description="vein (default) or force")]
ImageLayerQuery = Annotated[ImageLayer, Query(description="vein (default), force (0-30 N) or coverage (frames)")]


def get_results(request: Request) -> ResultsStore:
    """Return the application's ResultsStore (made on first use, over the settings' data_dir)."""
    rs = getattr(request.app.state, "results", None)
    if rs is None:
        rs = ResultsStore(request.app.state.settings.data_dir)
        request.app.state.results = rs
    return rs


Results = Annotated[ResultsStore, Depends(get_results)]


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


def reprocess_running(rs: ResultsStore, sid: str) -> bool:
    """Return True while a results version newer than the current one is neither finished nor failed."""
    current = rs.current_version(sid)
    if current is None:
        return False
    try:
        newer = [v for v in rs.list_versions(sid) if v > current]
    except FileNotFoundError:
        return False
    return any(not ((state := rs.read_state(sid, v) or {}).get("finished") or state.get("failed")) for v in newer)


def served_mosaic(rs: ResultsStore, sid: str, requested: int | None) -> tuple[int, dict[str, Any]]:
    """Return (version, mosaic.json + "results_version") or raise 404 when no frame has been processed yet."""
    v = resolve_version(rs, sid, requested)
    doc = rs.read_mosaic_meta(sid, v) if v is not None else None
    if v is None or doc is None:
        raise NotFound("no mosaic yet: no frame of this session has been processed", code="not_ready")
    return v, {**doc, "results_version": v}


def mosaic_etag(v: int, doc: dict[str, Any]) -> str:
    """Return the strong ETag of a mosaic.json: results version and the mosaic's change counter."""
    return f'"{v}.{int(doc.get("version", 0))}"'


def etag_matches(request: Request, etag: str) -> bool:
    """Return True if the request's If-None-Match lists `etag` (weak or strong) or is "*"."""
    header = request.headers.get("if-none-match")
    if not header:
        return False
    tags = [t.strip() for t in header.split(",")]
    return "*" in tags or any(t.removeprefix("W/") == etag for t in tags)


def _conditional(request: Request, etag: str, headers: dict[str, str]) -> Response | None:
    if etag_matches(request, etag):
        return Response(status_code=304, headers={**headers, "ETag": etag})
    return None


def path_row(d: dict[str, Any]) -> PathRow:
    """Return a PathRow from a path.json dict (null numbers become NaN)."""
    values = {}
    for c in PATH_COLUMNS:
        v = d.get(c)
        if c in _FLOAT_COLUMNS:
            v = math.nan if v is None else float(v)
        values[c] = v
    values["seq"] = int(values["seq"])
    values["inliers"] = int(values["inliers"] or 0)
    values["status"] = str(values["status"])
    values["reason"] = str(values.get("reason") or "")
    return PathRow(**values)


def extent_of(rs: ResultsStore, sid: str) -> dict[str, Any] | None:
    """Return the mosaic extent for GET /v1/sessions/{id} ({x,y}_{min,max}_mm, width/height mm) or None."""
    v = resolve_version(rs, sid, None)
    doc = rs.read_mosaic_meta(sid, v) if v is not None else None
    ext = (doc or {}).get("extent_mm")
    if not ext or len(ext) != 4:
        return None
    x0, y0, x1, y1 = (float(e) for e in ext)
    return {
        "xmin_mm": x0,
        "ymin_mm": y0,
        "xmax_mm": x1,
        "ymax_mm": y1,
        "width_mm": x1 - x0,
        "height_mm": y1 - y0,
        "results_version": v,
    }


# ----- path -----------------------------------------------------------------------------------------------------
@router.get(
    "/{session_id}/path",
    responses={200: {"content": {"application/json": {}, "text/csv": {}}, "description": "spec §4 path rows"}},
)
def get_path(
    meta: ViewSession,
    rs: Results,
    fmt: Annotated[Literal["json", "csv"], Query(alias="format")] = "json",
    v: VersionQuery = None,
) -> Response:
    """Return the probe path (spec §4): a JSON list of rows (null where not placed) or CSV; [] before any."""
    version = resolve_version(rs, meta.id, v)
    rows = (rs.read_path(meta.id, version) if version is not None else None) or []
    headers = {"Cache-Control": NO_CACHE, "X-Results-Version": str(version or 0)}
    if fmt == "csv":
        headers["Content-Disposition"] = 'attachment; filename="path.csv"'
        return Response(path_csv([path_row(d) for d in rows]), media_type="text/csv; charset=utf-8", headers=headers)
    return JSONResponse(rows, headers=headers)


# ----- mosaic ---------------------------------------------------------------------------------------------------
@router.get("/{session_id}/mosaic.json", responses={304: {"description": "not modified (ETag)"}})
def get_mosaic_json(meta: ViewSession, rs: Results, request: Request, v: VersionQuery = None) -> Response:
    """Return mosaic.json: spec §4 fields, version (changes with the mosaic), revisions, dzi, extent_mm."""
    version, doc = served_mosaic(rs, meta.id, v)
    etag = mosaic_etag(version, doc)
    headers = {"Cache-Control": NO_CACHE, "X-Results-Version": str(version)}
    return _conditional(request, etag, headers) or JSONResponse(doc, headers={**headers, "ETag": etag})


def _file_response(request: Request, path: Path, version: int, media_type: str, missing: str) -> Response:
    try:
        st = path.stat()
        data = path.read_bytes()
    except FileNotFoundError:
        raise NotFound(missing, code="not_ready") from None
    etag = f'"{version}-{st.st_mtime_ns:x}-{st.st_size:x}"'
    headers = {"Cache-Control": NO_CACHE, "X-Results-Version": str(version)}
    return _conditional(request, etag, headers) or Response(
        data, media_type=media_type, headers={**headers, "ETag": etag}
    )


@router.get("/{session_id}/mosaic.png", response_class=Response, responses={200: {"content": {"image/png": {}}}})
def get_mosaic_png(
    meta: ViewSession, rs: Results, request: Request, layer: ImageLayerQuery = "vein", v: VersionQuery = None
) -> Response:
    """Return the whole mosaic as PNG (8-bit gray; ?layer=force|coverage: the colour-coded layer, see legends)."""
    version = resolve_version(rs, meta.id, v)
    if version is None:
        raise NotFound("no mosaic yet: no frame of this session has been processed", code="not_ready")
    path = rs.image_path(meta.id, version, LAYER_IMAGES[layer])
    return _file_response(request, path, version, "image/png", "no mosaic image yet")


def dzi_xml(dzi: dict[str, Any]) -> str:
    """Return the Deep Zoom descriptor (XML) of a mosaic.json "dzi" block."""
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<Image TileSize="{int(dzi["tile_size"])}" Overlap="0" Format="png" '
        'xmlns="http://schemas.microsoft.com/deepzoom/2008">'
        f'<Size Width="{int(dzi["width"])}" Height="{int(dzi["height"])}"/></Image>\n'
    )


@router.get("/{session_id}/mosaic.dzi", response_class=Response, responses={200: {"content": {"application/xml": {}}}})
def get_dzi(
    meta: ViewSession, rs: Results, request: Request, layer: LayerQuery = "vein", v: VersionQuery = None
) -> Response:
    """Return the Deep Zoom descriptor; tiles are at mosaic_files/ (the same ?layer= and ?token= apply)."""
    version, doc = served_mosaic(rs, meta.id, v)
    dzi = doc.get("dzi")
    if not dzi:
        raise NotFound("no tiles yet", code="not_ready")
    body = dzi_xml(dzi)
    etag = f'"{version}-dzi-{int(dzi["width"])}x{int(dzi["height"])}-{int(dzi["tile_size"])}"'
    headers = {"Cache-Control": NO_CACHE, "X-Results-Version": str(version)}
    return _conditional(request, etag, headers) or Response(
        body, media_type="application/xml", headers={**headers, "ETag": etag}
    )


def tile_size_at(dzi: dict[str, Any], level: int, col: int, row: int) -> tuple[int, int] | None:
    """Return the (width, height) px of DZI tile (level, col, row), or None when it is out of range."""
    max_level, ts = int(dzi["max_level"]), int(dzi["tile_size"])
    if not 0 <= level <= max_level or col < 0 or row < 0:
        return None
    scale = 2 ** (max_level - level)
    lw, lh = math.ceil(int(dzi["width"]) / scale), math.ceil(int(dzi["height"]) / scale)
    if col * ts >= lw or row * ts >= lh:
        return None
    return min(ts, lw - col * ts), min(ts, lh - row * ts)


@lru_cache(maxsize=64)
def blank_tile(width: int, height: int) -> bytes:
    """Return a fully transparent RGBA PNG of width x height px."""
    ok, buf = cv2.imencode(".png", np.zeros((height, width, 4), np.uint8), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    return buf.tobytes()


@router.get(
    "/{session_id}/mosaic_files/{level:int}/{col:int}_{row:int}.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}, 404: {"description": "tile out of range"}},
)
def get_tile(
    meta: ViewSession,
    level: int,
    col: int,
    row: int,
    rs: Results,
    r: RedisClient,
    settings: AppSettings,
    layer: LayerQuery = "vein",
    rev: Annotated[int | None, Query(ge=0, description="tile revision from mosaic.json")] = None,
    v: VersionQuery = None,
) -> Response:
    """Return one Deep Zoom tile (PNG with alpha); a transparent tile where the mosaic has no data yet."""
    incr(r, settings.redis_prefix, "tile_hits_total")
    version, doc = served_mosaic(rs, meta.id, v)
    dzi = doc.get("dzi")
    size = tile_size_at(dzi, level, col, row) if dzi else None
    if size is None:
        raise NotFound("tile out of range", code="not_found")
    try:
        data = rs.tile_path(meta.id, version, layer, level, col, row).read_bytes()
    except FileNotFoundError:
        data = blank_tile(*size)
    known = int(((doc.get("revisions") or {}).get(layer) or {}).get(f"{level}/{col}_{row}", 0))
    cache = IMMUTABLE if (rev is not None and v is not None and rev <= known) else NO_CACHE
    return Response(data, media_type="image/png", headers={"Cache-Control": cache, "X-Results-Version": str(version)})


# ----- reference and accuracy report -------------------------------------------------------------------------------
def plot_url(sid: str, v: int, name: str) -> str:
    """Return the URL of a report plot."""
    return f"/v1/sessions/{sid}/plots/{name}.png?v={v}"


def parse_reference(
    store: SessionStore, sid: str, rows: list[dict[str, Any]], text: str
) -> tuple[list[int], np.ndarray]:
    """Return (the session's frame seqs, reference (N, 2) mm aligned to them); Validation naming the line."""
    ordered = sorted({f.seq for f in store.list_frames(sid)} | {int(d["seq"]) for d in rows})
    try:
        reference = parse_reference_csv(text, ordered)
    except ValueError as exc:
        raise Validation(str(exc), code="invalid_reference") from None
    if not np.any(np.all(np.isfinite(reference), axis=1)):
        raise Validation("reference.csv: no data rows (expected seq,x_mm,y_mm lines)", code="invalid_reference")
    return ordered, reference


def build_report(store: SessionStore, rs: ResultsStore, sid: str, v: int, reference_text: str) -> dict[str, Any]:
    """Evaluate version v's path against reference.csv, write the report's images and report.json; return it.

    Raises Validation naming the line for a bad reference, Conflict when version v has no path yet.
    """
    rows = rs.read_path(sid, v) or []
    ordered, reference_all = parse_reference(store, sid, rows, reference_text)
    if not rows:
        raise Conflict("no path yet: post the reference after frames have been processed", code="not_ready")
    position = {s: i for i, s in enumerate(ordered)}
    path = [path_row(d) for d in sorted(rows, key=lambda d: int(d["seq"]))]
    reference = reference_all[[position[p.seq] for p in path]]
    mosaic_doc = rs.read_mosaic_meta(sid, v) or {}
    mosaic = rs.read_mosaic_layers(sid, v)
    options = rs.read_options(sid, v) or {}
    extra = {
        "session": sid,
        "results_version": v,
        "mosaic_version": int(mosaic_doc.get("version", 0)),
        "path_rows": len(path),
        "method": options.get("method"),
    }
    try:
        report = build_session_report(path, reference, mosaic, extra, sheet=False)
    except ValueError as exc:
        raise Validation(f"reference.csv: {exc}", code="nothing_to_compare") from None
    if mosaic is None:  # still live: paths.png over the served mosaic image, as it is now
        report = _paths_over_live_mosaic(rs, sid, v, path, reference, mosaic_doc, report)
    for name, data in report.images.items():
        if name in IMAGE_FILES:
            rs.write_image(sid, v, name, data)
    doc = {**report.doc, "plots": {name: plot_url(sid, v, name) for name in PLOT_NAMES}}
    rs.write_report(sid, v, doc)
    return doc


def _paths_over_live_mosaic(
    rs: ResultsStore,
    sid: str,
    v: int,
    path: list[PathRow],
    reference: np.ndarray,
    mosaic_doc: dict[str, Any],
    report: SessionReport,
) -> SessionReport:
    try:
        raw = rs.image_path(sid, v, "mosaic.png").read_bytes()
    except FileNotFoundError:
        return report
    vein = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_GRAYSCALE)
    if vein is None or "origin_px" not in mosaic_doc or not mosaic_doc.get("px_per_mm"):
        return report
    estimate, registered = path_arrays(path)
    origin = (float(mosaic_doc["origin_px"][0]), float(mosaic_doc["origin_px"][1]))
    png = figure_bytes(
        plot_paths_over_mosaic, estimate, registered, reference, vein, float(mosaic_doc["px_per_mm"]), origin
    )
    return replace(report, images={**report.images, "paths.png": png})


async def _read_body(request: Request, limit: int) -> bytes:
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise PayloadTooLarge(f"request body larger than {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


@router.post(
    "/{session_id}/reference",
    responses={
        200: {"description": "the accuracy report (spec §4)"},
        409: {"description": "no path yet"},
        415: {"description": "not text/csv"},
        422: {"description": "bad reference.csv (the message names the line)"},
    },
)
async def post_reference(
    meta: IngestSession, request: Request, store: Store, rs: Results, settings: AppSettings
) -> JSONResponse:
    """Store reference.csv (seq,x_mm,y_mm) and return the accuracy report of the current results version."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in REFERENCE_TYPES:
        raise UnsupportedMediaType("reference: expected a text/csv body (seq,x_mm,y_mm)")
    body = await _read_body(request, settings.max_json_bytes)
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise Validation("reference.csv: not UTF-8 text", code="invalid_reference") from None
    version = resolve_version(rs, meta.id, None)
    if version is None:
        await run_in_threadpool(parse_reference, store, meta.id, [], text)  # a bad file is named first
        raise Conflict("no path yet: post the reference after frames have been processed", code="not_ready")
    doc = await run_in_threadpool(_store_and_report, store, rs, meta.id, version, text)
    log.info("reference evaluated", extra={"session": meta.id})
    return JSONResponse(doc, headers={"X-Results-Version": str(version)})


def _store_and_report(store: SessionStore, rs: ResultsStore, sid: str, v: int, text: str) -> dict[str, Any]:
    doc = build_report(store, rs, sid, v, text)  # validates before anything is stored
    rs.write_reference(sid, text)
    return doc


@router.get("/{session_id}/report", responses={404: {"description": "no reference posted yet"}})
async def get_report(meta: ViewSession, store: Store, rs: Results, v: VersionQuery = None) -> JSONResponse:
    """Return the accuracy report (spec §4) with plot links; recomputed when the path has changed since."""
    reference = await run_in_threadpool(rs.read_reference, meta.id)
    if reference is None:
        raise NotFound("no report: no reference track has been posted for this session", code="no_reference")
    version = resolve_version(rs, meta.id, v)
    if version is None:
        raise NotFound("no report: no frame has been processed yet", code="not_ready")
    doc = await run_in_threadpool(_fresh_report, store, rs, meta.id, version, reference)
    return JSONResponse(doc, headers={"Cache-Control": NO_CACHE, "X-Results-Version": str(version)})


def _fresh_report(store: SessionStore, rs: ResultsStore, sid: str, v: int, reference: str) -> dict[str, Any]:
    doc = rs.read_report(sid, v)
    mosaic_doc = rs.read_mosaic_meta(sid, v) or {}
    stale = doc is None or ("mosaic_version" in doc and int(doc["mosaic_version"]) != int(mosaic_doc.get("version", 0)))
    if stale:
        return build_report(store, rs, sid, v, reference)
    assert doc is not None
    return {**doc, "results_version": v, "plots": {name: plot_url(sid, v, name) for name in PLOT_NAMES}}


@router.get("/{session_id}/plots/{name}.png", response_class=Response, responses={200: {"content": {"image/png": {}}}})
def get_plot(
    meta: ViewSession, name: Literal["paths", "errors"], rs: Results, request: Request, v: VersionQuery = None
) -> Response:
    """Return a report plot: paths (estimate and reference over the mosaic) or errors (error along the scan)."""
    version = resolve_version(rs, meta.id, v)
    if version is None:
        raise NotFound("no report plots yet", code="not_ready")
    return _file_response(request, rs.image_path(meta.id, version, f"{name}.png"), version, "image/png", "no plot yet")


__all__ = ["Results", "extent_of", "get_results", "reprocess_running", "resolve_version", "router", "served_mosaic"]
