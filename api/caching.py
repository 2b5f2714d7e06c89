"""HTTP caching of results: ETags, 304 answers and the Cache-Control values every results route uses.

mosaic.json, the whole images and the DZI descriptor are "no-cache" with an ETag (304 on a matching
If-None-Match). A tile requested with both ?v= and ?rev= is immutable ("private": these are patient images
behind a credential, never for shared caches); without them it is "no-cache". Tile revisions restart in
every results version, hence v in the immutable URL.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import Request, Response

from api.errors import NotFound

IMMUTABLE = "private, max-age=31536000, immutable"
NO_CACHE = "no-cache"


def version_headers(version: int | None, cache: str = NO_CACHE) -> dict[str, str]:
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
    """Return `body` with its ETag and no-cache (304 when the client holds it)."""
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
