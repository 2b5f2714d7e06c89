"""The browser tile viewer: GET /viewer/{id} (static HTML) and the static assets it loads.

/static/ serves api/static (viewer.js, viewer.css); /static/vendor/openseadragon/ serves the pinned npm
package's build (node_modules/openseadragon/build/openseadragon, installed by `npm ci` at the repo root).
The page holds nothing about the session: viewer.js reads the session id from the URL path and the view-only
token from ?token=, and passes the token on to every API call. No referrer leaves the page (the URL
carries the token), and a strict Content-Security-Policy allows only this origin.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from api.deps import ViewSession
from api.errors import ServiceUnavailable

router = APIRouter(tags=["viewer"])

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
REPO_ROOT = Path(__file__).resolve().parents[2]
VENDOR_DIR = REPO_ROOT / "node_modules" / "openseadragon" / "build" / "openseadragon"
CSP = (
    "default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; script-src 'self'; "
    "connect-src 'self'; worker-src 'self' blob:; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
)
PAGE_HEADERS = {
    "Cache-Control": "no-store",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Content-Security-Policy": CSP,
}


@router.get("/viewer/{session_id}", response_class=FileResponse, responses={200: {"content": {"text/html": {}}}})
def viewer_page(meta: ViewSession) -> Response:
    """Return the viewer page for a session the caller may view (a viewer link's ?token= or a key)."""
    page = STATIC_DIR / "viewer.html"
    if not (VENDOR_DIR / "openseadragon.min.js").is_file():
        raise ServiceUnavailable("the viewer's assets are not installed (run `npm ci` at the repository root)")
    return FileResponse(page, media_type="text/html; charset=utf-8", headers=PAGE_HEADERS)


router.mount("/static/vendor/openseadragon", StaticFiles(directory=VENDOR_DIR, check_dir=False), name="osd")
router.mount("/static", StaticFiles(directory=STATIC_DIR, check_dir=False), name="static")
