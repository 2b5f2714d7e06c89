"""Results of a session (spec §4, §5): path, mosaic.json, whole images and Deep Zoom tiles.

Which version is served: api.results_access; caching and ETags: api.caching; the documents themselves are
built by services (documents, deepzoom) and only read here.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import JSONResponse

from api.caching import (
    PRIVATE_NO_STORE,
    cached_bytes,
    conditional,
    file_response,
    mosaic_etag,
    tile_cache,
    version_headers,
)
from api.deps import AppSettings, RedisClient, ViewSession, incr
from api.errors import NotFound
from api.results_access import Results, VersionQuery, resolve_version, served_mosaic, served_version
from services.core.mosaic.deepzoom import DziGeometry, blank_png
from services.core.path_rows import path_csv, path_rows_from_json

router = APIRouter(prefix="/v1/sessions", tags=["results"])

Layer = Literal["vein", "force"]
ImageLayer = Literal["vein", "force", "coverage"]
LAYER_IMAGES: dict[str, str] = {"vein": "mosaic.png", "force": "force.png", "coverage": "coverage.png"}
LayerQuery = Annotated[Layer, Query(description="vein (default) or force")]
ImageLayerQuery = Annotated[ImageLayer, Query(description="vein (default), force (0-30 N) or coverage (frames)")]


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
    headers = version_headers(version)
    if fmt == "csv":
        headers["Content-Disposition"] = 'attachment; filename="path.csv"'
        return Response(path_csv(path_rows_from_json(rows)), media_type="text/csv; charset=utf-8", headers=headers)
    return JSONResponse(rows, headers=headers)


@router.get("/{session_id}/mosaic.json", responses={304: {"description": "not modified (ETag)"}})
def get_mosaic_json(meta: ViewSession, rs: Results, request: Request, v: VersionQuery = None) -> Response:
    """Return mosaic.json: spec §4 fields, version (changes with the mosaic), revisions, dzi, extent_mm."""
    version, doc = served_mosaic(rs, meta.id, v)
    etag, headers = mosaic_etag(version, doc), version_headers(version)
    return conditional(request, etag, headers) or JSONResponse(doc, headers={**headers, "ETag": etag})


@router.get("/{session_id}/mosaic.png", response_class=Response, responses={200: {"content": {"image/png": {}}}})
def get_mosaic_png(
    meta: ViewSession, rs: Results, request: Request, layer: ImageLayerQuery = "vein", v: VersionQuery = None
) -> Response:
    """Return the whole mosaic as PNG (8-bit gray; ?layer=force|coverage: the colour-coded layer, see legends)."""
    version = served_version(rs, meta.id, v)
    path = rs.image_path(meta.id, version, LAYER_IMAGES[layer])
    return file_response(request, path, version, "image/png", "no mosaic image yet")


def _geometry(doc: dict) -> DziGeometry:
    """Return the served mosaic's Deep Zoom geometry; 404 not_ready before it has one."""
    if not doc.get("dzi"):
        raise NotFound("no tiles yet", code="not_ready")
    return DziGeometry.from_dict(doc["dzi"], float(doc.get("px_per_mm") or 1.0))


@router.get("/{session_id}/mosaic.dzi", response_class=Response, responses={200: {"content": {"application/xml": {}}}})
def get_dzi(
    meta: ViewSession, rs: Results, request: Request, layer: LayerQuery = "vein", v: VersionQuery = None
) -> Response:
    """Return the Deep Zoom descriptor; tiles are at mosaic_files/ (the same ?layer= and ?token= apply)."""
    version, doc = served_mosaic(rs, meta.id, v)
    g = _geometry(doc)
    etag = f'"{version}-dzi-{g.width}x{g.height}-{g.tile_size}"'
    return cached_bytes(request, g.dzi_xml(), etag, "application/xml", version)


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
    size = _geometry(doc).tile_size_px(level, col, row) if doc.get("dzi") else None
    if size is None:
        raise NotFound("tile out of range", code="not_found")
    try:
        data = rs.tile_path(meta.id, version, layer, level, col, row).read_bytes()
    except FileNotFoundError:
        data = blank_png(*size)
    known = int(((doc.get("revisions") or {}).get(layer) or {}).get(f"{level}/{col}_{row}", 0))
    versioned = rev is not None and v is not None and rev <= known
    cache = tile_cache(settings.tile_cache_max_age_s) if versioned else PRIVATE_NO_STORE
    return Response(data, media_type="image/png", headers=version_headers(version, cache))
