"""HTTP caching of results: ETags, 304 answers and the Cache-Control values every results route uses.

Results are patient data behind a credential: mosaic.json, the whole images, the DZI descriptor, the path and
the report are "private, no-store" (no cache keeps them, shared or the browser's), with an ETag (304 on a
matching If-None-Match, for clients that keep their own copy). A tile requested with both ?v= and ?rev= (a
revision it has reached) may be kept by the browser for `tile_cache_max_age_s` (5 minutes by default:
"private, max-age=300"), never by a shared cache; without them it is "private, no-store". Tile revisions
restart in every results version, hence v in the cacheable URL. Every other /v1/ answer is "private, no-store"
unless its route says otherwise (api.headers).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import Request, Response

from api.errors import NotFound

PRIVATE_NO_STORE = "private, no-store"


def tile_cache(max_age_s: int) -> str:
    """Return the Cache-Control of a versioned tile: the browser may keep it max_age_s seconds, no shared cache."""
    return f"private, max-age={int(max_age_s)}" if max_age_s > 0 else PRIVATE_NO_STORE


def version_headers(version: int | None, cache: str = PRIVATE_NO_STORE) -> dict[str, str]:
    """Return the Cache-Control and X-Results-Version headers of a results answer."""
    return {"Cache-Control": cache, "X-Results-Version": str(version or 0)}


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


def conditional(request: Request, etag: str, headers: dict[str, str]) -> Response | None:
    """Return a 304 answer when the request already holds `etag`, else None."""
    if etag_matches(request, etag):
        return Response(status_code=304, headers={**headers, "ETag": etag})
    return None


def cached_bytes(request: Request, body: bytes | str, etag: str, media_type: str, version: int) -> Response:
    """Return `body` with its ETag and "private, no-store" (304 when the client holds it)."""
    headers = version_headers(version)
    return conditional(request, etag, headers) or Response(
        body, media_type=media_type, headers={**headers, "ETag": etag}
    )


def file_response(request: Request, path: Path, version: int, media_type: str, missing: str) -> Response:
    """Return a stored file with an ETag of (version, mtime, size); 404 not_ready (message `missing`) if absent."""
    try:
        st = path.stat()
        data = path.read_bytes()
    except FileNotFoundError:
        raise NotFound(missing, code="not_ready") from None
    etag = f'"{version}-{st.st_mtime_ns:x}-{st.st_size:x}"'
    return cached_bytes(request, data, etag, media_type, version)
