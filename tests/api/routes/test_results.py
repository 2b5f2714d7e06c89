"""Results routes: path, mosaic.json (ETag/304), mosaic.png, DZI and tiles (cache headers); the reference and the
report: test_report.py.

Results are produced with the services code a worker uses (SessionReconstruction live + TilePyramid) on the
simulated "short" scan and written with ResultsStore (tests/api/results_bundle.py), so the routes are tested
against real files.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import pytest
from api_helpers import INGEST, auth
from fastapi.testclient import TestClient
from results_bundle import Bundle, create_session

from api.auth import make_viewer_token
from services.core.inputs.scan import Scan
from services.core.path_rows import PATH_COLUMNS
from services.store.results_store import ResultsStore


def _error(resp: Any) -> dict[str, Any]:
    body = resp.json()
    assert set(body) == {"error"}
    return body["error"]


# ----- path -------------------------------------------------------------------------------------------------------


def test_path_json_and_csv(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    resp = client.get(f"/v1/sessions/{sid}/path", headers=INGEST)
    assert resp.status_code == 200 and resp.headers["X-Results-Version"] == "1"
    rows = resp.json()
    assert len(rows) == len(bundle.rows) == 40
    assert list(rows[0]) == list(PATH_COLUMNS) and rows[0]["seq"] == 0 and rows[0]["status"] == "ok"
    # frame 0 is the origin of the path (spec §4), to the 4 decimals of the CSV
    assert abs(rows[0]["x_mm"]) < 1e-9 and abs(rows[0]["y_mm"]) < 1e-9

    csv_resp = client.get(f"/v1/sessions/{sid}/path?format=csv", headers=INGEST)
    assert csv_resp.status_code == 200 and csv_resp.headers["content-type"].startswith("text/csv")
    lines = csv_resp.text.strip().splitlines()
    assert lines[0] == ",".join(PATH_COLUMNS) and len(lines) == 41
    last = lines[-1].split(",")
    assert int(last[0]) == 39 and abs(float(last[2]) - rows[-1]["x_mm"]) < 1e-4  # CSV keeps 4 decimals

    assert client.get(f"/v1/sessions/{sid}/path?format=xml", headers=INGEST).status_code == 422


def test_path_before_results_is_empty(client: TestClient, short_scan: Scan) -> None:
    sid = create_session(client, short_scan)["id"]
    assert client.get(f"/v1/sessions/{sid}/path", headers=INGEST).json() == []
    assert client.get(f"/v1/sessions/{sid}/path?format=csv", headers=INGEST).text.strip() == ",".join(PATH_COLUMNS)
    resp = client.get(f"/v1/sessions/{sid}/mosaic.json", headers=INGEST)
    assert resp.status_code == 404 and _error(resp)["code"] == "not_ready"


# ----- mosaic.json, png, dzi ------------------------------------------------------------------------------------------


def test_mosaic_json_etag_and_304(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    resp = client.get(f"/v1/sessions/{sid}/mosaic.json", headers=INGEST)
    assert resp.status_code == 200
    doc = resp.json()
    for key in ("px_per_mm", "origin_px", "width", "height", "version", "revisions", "dzi", "extent_mm"):
        assert key in doc, key
    assert doc["results_version"] == 1 and doc["px_per_mm"] == 8.0
    assert resp.headers["Cache-Control"] == "private, no-store"  # patient data: kept by no cache
    etag = resp.headers["ETag"]
    assert etag == '"1.1"'

    again = client.get(f"/v1/sessions/{sid}/mosaic.json", headers={**INGEST, "If-None-Match": etag})
    assert again.status_code == 304 and again.content == b"" and again.headers["ETag"] == etag
    weak = client.get(f"/v1/sessions/{sid}/mosaic.json", headers={**INGEST, "If-None-Match": f'"x", W/{etag}'})
    assert weak.status_code == 304

    # the mosaic changes: a new version, a new ETag, and the old one no longer matches
    rs = ResultsStore(client.app.state.settings.data_dir)  # type: ignore[attr-defined]
    rs.write_mosaic_meta(sid, 1, {**bundle.doc, "version": 2})
    changed = client.get(f"/v1/sessions/{sid}/mosaic.json", headers={**INGEST, "If-None-Match": etag})
    assert changed.status_code == 200 and changed.headers["ETag"] == '"1.2"' and changed.json()["version"] == 2


def test_mosaic_png_layers(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    resp = client.get(f"/v1/sessions/{sid}/mosaic.png", headers=INGEST)
    assert resp.status_code == 200 and resp.headers["content-type"] == "image/png"
    vein = cv2.imdecode(np.frombuffer(resp.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert vein.shape == (bundle.doc["height"], bundle.doc["width"])
    assert (
        client.get(
            f"/v1/sessions/{sid}/mosaic.png", headers={**INGEST, "If-None-Match": resp.headers["ETag"]}
        ).status_code
        == 304
    )
    force = client.get(f"/v1/sessions/{sid}/mosaic.png?layer=force", headers=INGEST)
    img = cv2.imdecode(np.frombuffer(force.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (*vein.shape, 3)
    bad = client.get(f"/v1/sessions/{sid}/mosaic.png?layer=pressure", headers=INGEST)
    assert bad.status_code == 422 and "layer" in _error(bad)["message"]


def test_dzi_descriptor(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    resp = client.get(f"/v1/sessions/{sid}/mosaic.dzi?layer=force", headers=INGEST)
    assert resp.status_code == 200 and "xml" in resp.headers["content-type"]
    root = ET.fromstring(resp.text)
    ns = "{http://schemas.microsoft.com/deepzoom/2008}"
    assert root.tag == f"{ns}Image" and root.get("TileSize") == "256" and root.get("Format") == "png"
    size = root.find(f"{ns}Size")
    assert size is not None and int(size.get("Width", 0)) == bundle.doc["dzi"]["width"]


# ----- tiles ---------------------------------------------------------------------------------------------------------


def _decode(content: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)


def test_tile_with_data_and_cache_headers(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    dzi = bundle.doc["dzi"]
    top = dzi["max_level"]
    key, rev = next((k, r) for k, r in bundle.doc["revisions"]["vein"].items() if k.startswith(f"{top}/"))
    level, rest = key.split("/")
    url = f"/v1/sessions/{sid}/mosaic_files/{level}/{rest}.png"
    resp = client.get(f"{url}?v=1&rev={rev}", headers=INGEST)
    assert resp.status_code == 200 and resp.headers["content-type"] == "image/png"
    assert resp.headers["Cache-Control"] == "private, max-age=300"  # the browser's only, and not for a year
    col, row = (int(x) for x in rest.split("_"))
    assert resp.content == bundle.tiles[("vein", int(level), col, row)]
    img = _decode(resp.content)
    assert img.ndim == 3 and img.shape[2] in (2, 4)  # gray + alpha (OpenCV reads LA as BGRA)
    assert (img[..., -1] > 0).any()

    plain = client.get(url, headers=INGEST)
    assert plain.headers["Cache-Control"] == "private, no-store" and plain.content == resp.content
    # a revision newer than the one published is not kept (the tile may not be written yet)
    assert client.get(f"{url}?v=1&rev={rev + 5}", headers=INGEST).headers["Cache-Control"] == "private, no-store"
    force = client.get(f"{url}?layer=force&v=1&rev={rev}", headers=INGEST)
    assert force.content == bundle.tiles[("force", int(level), col, row)]


def test_blank_and_out_of_range_tiles(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    dzi = bundle.doc["dzi"]
    top = dzi["max_level"]
    base = f"/v1/sessions/{sid}/mosaic_files"
    assert "0/0_0" in bundle.doc["revisions"]["vein"]  # level 0 (1x1 px) always holds the whole mosaic
    assert f"{top}/0_0" not in bundle.doc["revisions"]["vein"]  # the corner is 200 mm from frame 0
    blank = client.get(f"{base}/{top}/0_0.png?v=1&rev=0", headers=INGEST)
    assert blank.status_code == 200
    img = _decode(blank.content)
    assert img.shape[:2] == (256, 256) and img.shape[2] == 4 and not img[..., 3].any()
    small = _decode(client.get(f"{base}/3/0_0.png", headers=INGEST).content)  # level 3: 8x8 px with data
    assert small.shape[:2] == (dzi["width"] // 2 ** (top - 3),) * 2

    cols = -(-dzi["width"] // 256)
    for path in (f"{top + 1}/0_0", f"{top}/{cols}_0", f"{top}/0_{cols}", "0/1_0"):
        resp = client.get(f"{base}/{path}.png", headers=INGEST)
        assert resp.status_code == 404, path
    assert client.get(f"{base}/{top}/a_b.png", headers=INGEST).status_code == 404


def test_tile_hits_are_counted(ready: tuple[TestClient, str, dict]) -> None:
    client, sid, _ = ready
    r = client.app.state.redis  # type: ignore[attr-defined]
    key = f"{client.app.state.settings.redis_prefix}metrics"  # type: ignore[attr-defined]
    before = int(r.hget(key, "tile_hits_total") or 0)
    for _ in range(3):
        client.get(f"/v1/sessions/{sid}/mosaic_files/0/0_0.png", headers=INGEST)
    assert int(r.hget(key, "tile_hits_total")) == before + 3


# ----- versions -----------------------------------------------------------------------------------------------------


def test_version_selection_while_reprocessing(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    rs = ResultsStore(client.app.state.settings.data_dir)  # type: ignore[attr-defined]
    assert rs.create_version(sid, {"method": "paper"}) == 2  # current, still empty
    resp = client.get(f"/v1/sessions/{sid}/mosaic.json", headers=INGEST)
    assert resp.status_code == 200 and resp.headers["X-Results-Version"] == "1"  # the previous results stay
    assert client.get(f"/v1/sessions/{sid}/mosaic.json?v=2", headers=INGEST).status_code == 404
    missing = client.get(f"/v1/sessions/{sid}/path?v=9", headers=INGEST)
    assert missing.status_code == 404 and _error(missing)["code"] == "no_such_version"
    rs.write_mosaic_meta(sid, 2, {**bundle.doc, "version": 1, "results_version": 2})
    resp = client.get(f"/v1/sessions/{sid}/mosaic.json", headers=INGEST)
    assert resp.headers["X-Results-Version"] == "2" and resp.headers["ETag"] == '"2.1"'


# ----- auth on every view route ---------------------------------------------------------------------------------------

VIEW_ROUTES = (
    "/path",
    "/path?format=csv",
    "/mosaic.json",
    "/mosaic.png",
    "/mosaic.png?layer=force",
    "/mosaic.dzi",
    "/mosaic_files/0/0_0.png",
)


def test_view_routes_auth(ready: tuple[TestClient, str, dict], short_scan: Scan) -> None:
    client, sid, created = ready
    other = create_session(client, short_scan, key=auth("ingest-key-b-0123456789abcdef"))
    token, other_token = created["viewer_token"], other["viewer_token"]
    secret = client.app.state.token_secrets  # type: ignore[attr-defined]
    expired = make_viewer_token(secret, sid, 10, now=1000.0)
    for route in VIEW_ROUTES:
        url = f"/v1/sessions/{sid}{route}"
        sep = "&" if "?" in url else "?"
        assert client.get(url).status_code == 401, route
        assert client.get(url, headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404, route  # not the owner
        assert client.get(url, headers=auth("view-key-0123456789abcdef")).status_code == 404, (
            route
        )  # view scope, not owner
        assert client.get(url, headers=auth("admin-key-0123456789abcdef")).status_code == 200, route
        assert client.get(url, headers=INGEST).status_code == 200, route
        assert client.get(f"{url}{sep}token={token}").status_code == 200, route
        assert client.get(f"{url}{sep}token={other_token}").status_code == 401, route  # token of another session
        assert client.get(f"{url}{sep}token={expired}").status_code == 401, route
        assert client.get(url, headers={"Authorization": f"Bearer {token}"}).status_code == 200, route
    # another key's session is indistinguishable from a missing one
    assert _error(client.get(f"/v1/sessions/{other['id']}/mosaic.json", headers=INGEST))["code"] == "not_found"


def test_extent_helper(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    from api.results_access import session_extent

    client, sid, _ = ready
    ext = session_extent(ResultsStore(client.app.state.settings.data_dir), sid)  # type: ignore[attr-defined]
    assert ext is not None and ext["results_version"] == 1
    assert ext["width_mm"] == pytest.approx(bundle.doc["extent_mm"][2] - bundle.doc["extent_mm"][0])
    assert re.match(r"^[0-9a-f]{32}$", sid)
    state = client.get(f"/v1/sessions/{sid}", headers=INGEST).json()  # the session state carries it too
    assert state["extent"] == ext


def test_a_token_signed_with_a_previous_secret_still_opens_the_view(
    make_client: Callable[..., TestClient], short_scan: Scan
) -> None:
    # previous_token_secrets reaches the app: a link signed before the secret was rotated still verifies
    old = "previous-secret-0123456789abcdef-01"
    client = make_client(previous_token_secrets=[old])
    sid = create_session(client, short_scan)["id"]
    now = client.app.state.clock()  # type: ignore[attr-defined]
    token = make_viewer_token(old.encode(), sid, 600, now=now)
    assert client.get(f"/v1/sessions/{sid}?token={token}").status_code == 200
    stranger = make_viewer_token(b"some-other-secret-0123456789abcdef", sid, 600, now=now)
    assert client.get(f"/v1/sessions/{sid}?token={stranger}").status_code == 401
