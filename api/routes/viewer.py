"""The browser tile viewer: GET /viewer/{id} (static HTML) and the static assets it loads.

/static/ serves api/static (viewer.js, viewer.css); /static/vendor/openseadragon/ serves the pinned npm
package's build: the copy an installed wheel carries in api/static/vendor/openseadragon (setup.py puts it there
at build time; never in git), else the checkout's node_modules/openseadragon/build/openseadragon (`npm ci`).
The page holds nothing about the session: viewer.js reads the session id from the URL path and the view-only
token from ?token=, keeps it in memory for every API call and takes it out of the address bar
(history.replaceState), so it stays in no history entry. No referrer leaves the page (its first URL carries
the token), and a strict Content-Security-Policy allows only this origin.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from api.deps import AppSettings, ViewSession
from api.errors import ServiceUnavailable
from services.settings import Settings

router = APIRouter(tags=["viewer"])

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
PACKAGED_OSD = STATIC_DIR / "vendor" / "openseadragon"  # in an installed wheel (setup.py's build hook)
REPO_ROOT = Path(__file__).resolve().parents[2]
OSD_BUILD = Path("node_modules") / "openseadragon" / "build" / "openseadragon"


def vendor_dir(settings: Settings) -> Path:
    """Return OpenSeadragon's build folder: the setting, the wheel's copy, the checkout's node_modules, the cwd's."""
    if settings.viewer_assets_dir is not None:
        return Path(settings.viewer_assets_dir)
    for folder in (PACKAGED_OSD, REPO_ROOT / OSD_BUILD, Path.cwd() / OSD_BUILD):
        if (folder / "openseadragon.min.js").is_file():
            return folder
    return REPO_ROOT / OSD_BUILD


def mount_static(app: FastAPI, settings: Settings) -> None:
    """Serve the viewer's own files and the installed OpenSeadragon under /static."""
    app.mount("/static/vendor/openseadragon", StaticFiles(directory=vendor_dir(settings), check_dir=False), name="osd")
    app.mount("/static", StaticFiles(directory=STATIC_DIR, check_dir=False), name="static")


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
def viewer_page(meta: ViewSession, settings: AppSettings) -> Response:
    """Return the viewer page for a session the caller may view (a viewer link's ?token= or a key)."""
    page = STATIC_DIR / "viewer.html"
    if not (vendor_dir(settings) / "openseadragon.min.js").is_file():
        raise ServiceUnavailable(
            "the viewer's assets are not installed (install a wheel built with them, or run `npm ci` in a checkout)"
        )
    return FileResponse(page, media_type="text/html; charset=utf-8", headers=PAGE_HEADERS)
