"""Results routes: path, mosaic.json (ETag/304), mosaic.png, DZI and tiles (cache headers), reference and report.

Results are produced with the services code a worker uses (SessionReconstruction live + TilePyramid) on the
simulated "short" scan and written with ResultsStore, so the routes are tested against real files.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from api_helpers import INGEST, auth, upload
from fastapi.testclient import TestClient

from api.auth import make_viewer_token
from services.core.inputs.scan import Scan
from services.core.methods import method_options
from services.core.mosaic.canvas import force_to_color
from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
from services.core.outputs.evaluation import evaluate_path
from services.core.pipeline import frame_forces, prepared_frames, window_radius_mm, window_setup
from services.core.session_reconstruction import PATH_COLUMNS, PathRow, SessionReconstruction, path_rows_json
from services.store.results_store import LAYERS, ResultsStore
from tests.sim_cache import simulated

# ----- a results bundle made with the workers' services code -----------------------------------------------------


@dataclass(frozen=True)
class Bundle:
    """What a worker would have written for one results version (in memory)."""

    path_rows: list[PathRow]
    tiles: dict[tuple[str, int, int, int], bytes]  # (layer, level, col, row) -> PNG
    doc: dict[str, Any]  # mosaic.json
    mosaic_png: bytes
    force_png: bytes
    truth_mm: np.ndarray  # (N, 2) true frame positions in frame 0's coordinates

    @property
    def rows(self) -> list[dict[str, Any]]:
        """Return the path rows as path.json holds them."""
        return path_rows_json(self.path_rows)


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def make_bundle(scan: Scan, n_frames: int | None = None, final: bool = True, mosaic_version: int = 1) -> Bundle:
    """Return the results of the first n_frames of `scan`, as the live workers would write them."""
    n = len(scan) if n_frames is None else n_frames
    part = replace(scan, frame_seq=scan.frame_seq[:n], frame_t_s=scan.frame_t_s[:n])
    options = method_options("best")
    calib = scan.calibration
    mask, flat = window_setup(part, options)
    recon = SessionReconstruction(calib, options, window_radius_mm(mask, calib), live=True)
    touched: set[tuple[int, int]] = set()
    for pf in prepared_frames(part, frame_forces(part), mask, flat, options):
        touched |= recon.add(pf)[1]
    if final:
        touched |= recon.finish()
    geometry = DziGeometry.for_mosaic(calib.px_per_mm)
    pyramid = TilePyramid(geometry)
    tiles: dict[tuple[str, int, int, int], bytes] = {}
    revisions: dict[str, dict[str, int]] = {layer: {} for layer in LAYERS}
    for level, col, row in pyramid.update(recon.canvas, touched):
        for layer in LAYERS:
            png = pyramid.render_png(level, col, row, layer)
            if png is not None:
                tiles[(layer, level, col, row)] = png
                revisions[layer][f"{level}/{col}_{row}"] = mosaic_version
    rows = recon.path_rows()
    mosaic = recon.canvas.render()
    ok = [r for r in rows if r.status == "ok"]
    radius = recon.window_radius_mm
    extent = [
        min(r.x_mm for r in ok) - radius,
        min(r.y_mm for r in ok) - radius,
        max(r.x_mm for r in ok) + radius,
        max(r.y_mm for r in ok) + radius,
    ]
    doc = {
        **mosaic.meta(),
        "version": mosaic_version,
        "revisions": revisions,
        "dzi": geometry.to_dict(),
        "extent_mm": extent,
        "frames": {"processed": len(rows), "ok": len(ok), "lost": 0, "rejected": 0, "no_contact": 0, "in_fragments": 0},
        "status": "done" if final else "processing",
    }
    truth = np.asarray(scan.truth["poses"], float)[:n, :2]
    return Bundle(rows, tiles, doc, _png(mosaic.vein), _png(force_to_color(mosaic.force_n)), truth)


def install(data_dir: Path, sid: str, bundle: Bundle, version: int = 1) -> ResultsStore:
    """Write a bundle as results version `version` of session `sid` (the way the workers do)."""
    rs = ResultsStore(data_dir)
    rs.ensure_version(sid, version, {"method": "best"})
    for (layer, level, col, row), png in bundle.tiles.items():
        rs.write_tile(sid, version, layer, level, col, row, png)
    rs.write_image(sid, version, "mosaic.png", bundle.mosaic_png)
    rs.write_image(sid, version, "force.png", bundle.force_png)
    rs.write_mosaic_meta(sid, version, {**bundle.doc, "results_version": version})
    rs.write_path(sid, version, bundle.path_rows)
    return rs


@pytest.fixture(scope="module")
def short_scan() -> Scan:
    """Return the simulated "short" scan (40 frames, seed 1)."""
    return simulated("short", 1)  # made once per run, shared with other modules


@pytest.fixture(scope="module")
def bundle(short_scan: Scan) -> Bundle:
    """Return the finished results of the whole short scan."""
    return make_bundle(short_scan)


def create_session(client: TestClient, scan: Scan, key: dict[str, str] = INGEST) -> dict[str, Any]:
    """Create a session with the scan's calibration; return the 201 body."""
    resp = client.post(
        "/v1/sessions", json={"calibration": scan.calibration.to_dict(), "label": "Jane Doe 1970"}, headers=key
    )
    assert resp.status_code == 201, resp.text
    return resp.json()


@pytest.fixture
def ready(client: TestClient, short_scan: Scan, bundle: Bundle) -> tuple[TestClient, str, dict[str, Any]]:
    """Return (client, session id, create body) of a session whose results are installed."""
    created = create_session(client, short_scan)
    install(client.app.state.settings.data_dir, created["id"], bundle)  # type: ignore[attr-defined]
    return client, created["id"], created


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
    other = create_session(client, short_scan, key=auth("ingest-key-b"))
    token, other_token = created["viewer_token"], other["viewer_token"]
    secret = client.app.state.token_secret  # type: ignore[attr-defined]
    expired = make_viewer_token(secret, sid, 10, now=1000.0)
    for route in VIEW_ROUTES:
        url = f"/v1/sessions/{sid}{route}"
        sep = "&" if "?" in url else "?"
        assert client.get(url).status_code == 401, route
        assert client.get(url, headers=auth("ingest-key-b")).status_code == 404, route  # not the owner
        assert client.get(url, headers=auth("view-key")).status_code == 404, route  # view scope, not owner
        assert client.get(url, headers=auth("admin-key")).status_code == 200, route
        assert client.get(url, headers=INGEST).status_code == 200, route
        assert client.get(f"{url}{sep}token={token}").status_code == 200, route
        assert client.get(f"{url}{sep}token={other_token}").status_code == 401, route  # token of another session
        assert client.get(f"{url}{sep}token={expired}").status_code == 401, route
        assert client.get(url, headers={"Authorization": f"Bearer {token}"}).status_code == 200, route
    # another key's session is indistinguishable from a missing one
    assert _error(client.get(f"/v1/sessions/{other['id']}/mosaic.json", headers=INGEST))["code"] == "not_found"


# ----- reference and report -----------------------------------------------------------------------------------------


def reference_csv(truth_mm: np.ndarray, seqs: range | list[int] | None = None) -> str:
    """Return reference.csv text for the given seqs (all by default) from true positions in mm."""
    seqs = range(len(truth_mm)) if seqs is None else seqs
    lines = ["seq,x_mm,y_mm", *(f"{s},{truth_mm[s, 0]:.6f},{truth_mm[s, 1]:.6f}" for s in seqs)]
    return "\n".join(lines) + "\n"


def post_reference(client: TestClient, sid: str, text: str, **headers: str) -> Any:
    """POST a reference.csv body; return the response."""
    return client.post(
        f"/v1/sessions/{sid}/reference",
        content=text.encode(),
        headers={**INGEST, "Content-Type": "text/csv", **headers},
    )


def test_reference_report_and_plots(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, created = ready
    assert client.get(f"/v1/sessions/{sid}/report", headers=INGEST).status_code == 404
    resp = post_reference(client, sid, reference_csv(bundle.truth_mm))
    assert resp.status_code == 200, resp.text
    report = resp.json()
    estimate = np.array([[r["x_mm"], r["y_mm"]] for r in bundle.rows], float)
    expected = evaluate_path(estimate, np.array([r["status"] == "ok" for r in bundle.rows]), bundle.truth_mm)
    # the route evaluates the same path against the same reference: equal up to the CSV's 6 decimals
    assert math.isclose(report["rmse_mm"], expected.rmse_mm, abs_tol=1e-5)
    assert report["rmse_mm"] < 2.0  # the short scan registers to about a millimetre or better
    assert expected.global_error is not None  # where the error lies, as the offline report.json has it
    # the same fit on the same frames; the CSV's 6 decimals move a ~50 mm path's scale by ~1e-6 %, 1e-3 % is loose
    assert math.isclose(report["global_error"]["scale_pct"], expected.global_error.scale_pct, abs_tol=1e-3)
    assert report["n_frames"] == 40 and report["registered_fraction"] == 1.0 and report["results_version"] == 1
    assert set(report["plots"]) == {"paths", "errors"}
    for url in report["plots"].values():
        plot = client.get(url, headers=INGEST)
        assert plot.status_code == 200 and plot.content.startswith(b"\x89PNG")
        assert _decode(plot.content).shape[0] > 200
        assert client.get(f"{url}&token={created['viewer_token']}").status_code == 200

    for url in (f"/v1/sessions/{sid}/report", report["plots"]["paths"]):
        assert client.get(url).status_code == 401
        assert client.get(url, headers=auth("ingest-key-b")).status_code == 404
        assert client.get(url, headers=auth("admin-key")).status_code == 200
    got = client.get(f"/v1/sessions/{sid}/report", headers=INGEST)
    assert got.status_code == 200 and got.json()["rmse_mm"] == report["rmse_mm"]
    assert client.get(f"/v1/sessions/{sid}/report?token={created['viewer_token']}").status_code == 200
    # the report follows the path: a new mosaic version makes GET /report evaluate again
    rs = ResultsStore(client.app.state.settings.data_dir)  # type: ignore[attr-defined]
    rs.write_mosaic_meta(sid, 1, {**bundle.doc, "version": 7})
    assert client.get(f"/v1/sessions/{sid}/report", headers=INGEST).json()["mosaic_version"] == 7


def test_partial_reference_compares_known_rows(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    resp = post_reference(client, sid, reference_csv(bundle.truth_mm, list(range(0, 40, 3))))
    assert resp.status_code == 200 and resp.json()["n_with_reference"] == 14 and resp.json()["n_compared"] == 14


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ("seq,x,y\n0,0,0\n", "line 1"),
        ("seq,x_mm,y_mm\n0,0,0\n1,abc,2\n", "line 3"),
        ("seq,x_mm,y_mm\n0,0,0\n0,1,1\n", "line 3"),
        ("seq,x_mm,y_mm\n0,0\n", "line 2"),
        ("seq,x_mm,y_mm\n0,0,nan\n", "line 2"),
        ("seq,x_mm,y_mm\n999,0,0\n", "seq 999"),
        ("seq,x_mm,y_mm\n", "no data rows"),
    ],
)
def test_bad_reference_is_422_naming_the_line(ready: tuple[TestClient, str, dict], body: str, needle: str) -> None:
    client, sid, _ = ready
    resp = post_reference(client, sid, body)
    assert resp.status_code == 422, resp.text
    err = _error(resp)
    assert err["code"] == "invalid_reference" and needle in err["message"]
    assert client.get(f"/v1/sessions/{sid}/report", headers=INGEST).status_code == 404  # nothing stored


def test_reference_media_type_auth_and_not_ready(
    ready: tuple[TestClient, str, dict], client: TestClient, short_scan: Scan, bundle: Bundle
) -> None:
    _, sid, created = ready
    text = reference_csv(bundle.truth_mm)
    assert post_reference(client, sid, text, **{"Content-Type": "application/json"}).status_code == 415
    assert post_reference(client, sid, text, Authorization="Bearer ingest-key-b").status_code == 404
    assert post_reference(client, sid, text, Authorization="Bearer view-key").status_code == 403
    assert post_reference(client, sid, text, Authorization=f"Bearer {created['viewer_token']}").status_code == 401
    bad_utf8 = client.post(
        f"/v1/sessions/{sid}/reference",
        content=b"seq,x_mm,y_mm\n0,\xff,0\n",
        headers={**INGEST, "Content-Type": "text/csv"},
    )
    assert bad_utf8.status_code == 422 and "UTF-8" in _error(bad_utf8)["message"]
    fresh = create_session(client, short_scan)["id"]
    resp = post_reference(client, fresh, text.splitlines()[0] + "\n")
    assert resp.status_code == 422  # a bad file is named even before there is a path
    resp = post_reference(client, fresh, "seq,x_mm,y_mm\n")
    assert resp.status_code == 422
    no_frame = post_reference(client, fresh, "seq,x_mm,y_mm\n0,0,0\n")
    # seq 0 is not a frame of a session without uploads: named as such
    assert no_frame.status_code == 422 and "seq 0" in _error(no_frame)["message"]
    assert upload(client, fresh, 0, _png(short_scan.frame(0))).status_code == 202
    not_ready = post_reference(client, fresh, "seq,x_mm,y_mm\n0,0,0\n")
    assert not_ready.status_code == 409 and _error(not_ready)["code"] == "not_ready"


def test_extent_helper(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    from api.results_access import session_extent

    client, sid, _ = ready
    ext = session_extent(ResultsStore(client.app.state.settings.data_dir), sid)  # type: ignore[attr-defined]
    assert ext is not None and ext["results_version"] == 1
    assert ext["width_mm"] == pytest.approx(bundle.doc["extent_mm"][2] - bundle.doc["extent_mm"][0])
    assert re.match(r"^[0-9a-f]{32}$", sid)
    state = client.get(f"/v1/sessions/{sid}", headers=INGEST).json()  # the session state carries it too
    assert state["extent"] == ext
