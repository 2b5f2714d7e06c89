"""The viewer in a real headless Chromium against the real service (API + worker processes + Redis).

Part of the simulated "short" scan is uploaded frame by frame with the HTTP client; the viewer page (opened
with the session's viewer link) must show vein pixels where the frames were placed and nothing elsewhere;
the rest of the scan is uploaded and the canvas must grow. A screenshot goes to tests/artifacts/viewer.png.
"""

from __future__ import annotations

import base64
import contextlib
import time
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import pytest
from browser_service import ARTIFACTS, CHROMIUM, CHROMIUM_ARGS, browser_service

from cli.client import FORCE_LEAD_S, VeinmosaicClient
from cli.launcher import Service
from services.core.inputs.scan import Scan
from tests.sim_cache import simulated

pytestmark = pytest.mark.slow

KEY = "browser-test-key-0123456789abcdef"
FIRST_PART = 26  # the workers compute the window mask from the first 24 frames: the view starts after them
WAIT_S = 60.0


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """Start Redis (REDIS_URL, else embedded), one worker process and the API on a free port."""
    config = {"flush_every_s": 0.3, "image_every_s": 0.5, "lost_timeout_s": 5}
    with browser_service(tmp_path_factory.mktemp("browser") / "data", KEY, workers=1, worker_config=config) as svc:
        yield svc


@pytest.fixture(scope="module")
def scan() -> Scan:
    """Return the simulated short scan (40 frames)."""
    return simulated("short", 1)  # made once per run, shared with other modules


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def upload_frames(client: VeinmosaicClient, sid: str, scan: Scan, seqs: range) -> None:
    """Upload the forces up to the last frame (+ lead) and the frames `seqs`, one by one, as a device would."""
    forces = np.column_stack([scan.force_t_s, scan.forces_n])
    t_last = float(scan.frame_t_s[seqs[-1]]) + FORCE_LEAD_S
    t_first = float(scan.frame_t_s[seqs[0]]) + FORCE_LEAD_S if seqs[0] > 0 else -np.inf
    batch = forces[(forces[:, 0] > t_first) & (forces[:, 0] <= t_last)]
    if seqs[-1] == len(scan) - 1:
        batch = forces[forces[:, 0] > t_first]  # the rest of the force stream
    client.upload_forces(sid, batch)
    for seq in seqs:
        client.upload_frame(sid, seq, float(scan.frame_t_s[seq]), _png(scan.frame(seq)), f"{seq:06d}.png")


def wait_until(predicate: Any, what: str, timeout_s: float = WAIT_S) -> Any:
    """Poll `predicate` until it returns a truthy value; fail naming `what` after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    pytest.fail(f"timed out waiting for {what}")


CANVAS_JS = """() => {
  const v = window.veinmosaicViewer;
  const c = v.viewer.drawer.canvas;
  const vp = v.viewer.viewport;
  const p0 = vp.pixelFromPoint(new OpenSeadragon.Point(0, 0), true);
  const p1 = vp.pixelFromPoint(new OpenSeadragon.Point(1, 0), true);
  return {
    png: c.toDataURL("image/png"),
    ratio: c.width / c.clientWidth,
    p0: [p0.x, p0.y],
    s: (p1.x - p0.x) / v.state.dzi.width,
    origin: v.state.dzi.origin_px,
    ppm: v.state.pxPerMm,
    pathPoints: v.state.path.size,
    polyline: Array.from(document.querySelectorAll("#path-overlay polyline"))
      .map((l) => l.getAttribute("points").split(" ").filter(Boolean).length).reduce((a, b) => a + b, 0),
    strokes: document.querySelectorAll("#path-overlay polyline").length,
  };
}"""


class CanvasView:
    """The viewer canvas (BGRA) and the map from canvas pixels to frame 0's millimetres."""

    def __init__(self, doc: dict[str, Any]) -> None:
        raw = base64.b64decode(doc["png"].split(",", 1)[1])
        self.bgra = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
        assert self.bgra is not None and self.bgra.shape[2] == 4
        self.doc = doc
        self.mm_per_canvas_px = 1.0 / (doc["s"] * doc["ratio"] * doc["ppm"])

    def mm_of(self, cx: np.ndarray, cy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the mm coordinates (frame 0's axes) of canvas pixel centres."""
        d = self.doc
        ex, ey = (cx + 0.5) / d["ratio"], (cy + 0.5) / d["ratio"]
        dzi_x, dzi_y = (ex - d["p0"][0]) / d["s"], (ey - d["p0"][1]) / d["s"]
        return (dzi_x - d["origin"][0]) / d["ppm"], (dzi_y - d["origin"][1]) / d["ppm"]

    def covered(self) -> np.ndarray:
        """Return the mask of canvas pixels where the mosaic has data (alpha > 0)."""
        return self.bgra[..., 3] > 0

    def covered_area_mm2(self) -> float:
        """Return the area (mm^2) of covered canvas pixels."""
        return float(self.covered().sum()) * self.mm_per_canvas_px**2


def check_matches_path(view: CanvasView, rows: list[dict[str, Any]], radius_mm: float) -> dict[str, float]:
    """Assert: covered near placed frame centres, uncovered far from all; vein-like pixels; return stats."""
    centres = np.array([[r["x_mm"], r["y_mm"]] for r in rows if r["status"] == "ok"], float)
    h, w = view.bgra.shape[:2]
    ys, xs = np.mgrid[0:h:4, 0:w:4]
    mx, my = view.mm_of(xs.astype(float), ys.astype(float))
    pts = np.stack([mx.ravel(), my.ravel()], axis=1)
    dist = np.min(np.linalg.norm(pts[:, None, :] - centres[None, :, :], axis=2), axis=1)
    cov = view.covered()[ys.ravel(), xs.ravel()]
    inner, outer = dist < 0.5 * radius_mm, dist > 1.5 * radius_mm
    assert inner.sum() > 200 and outer.sum() > 200, (inner.sum(), outer.sum())
    inner_cov, outer_cov = float(cov[inner].mean()), float(cov[outer].mean())
    # near a placed frame's centre the mosaic is drawn; well outside every window nothing is (transparent)
    assert inner_cov > 0.97, inner_cov
    assert outer_cov < 0.02, outer_cov
    gray = view.bgra[..., :3].astype(float).mean(axis=2)[view.covered()]
    median, p2 = float(np.median(gray)), float(np.percentile(gray, 2))
    # vein-like content, not a flat fill: spread in brightness and a tail of dark (vessel) pixels
    # (realistic veins are 3-35 % darker and soft: measured p2 = median - 25 on the realistic short scan)
    assert gray.std() > 8.0 and p2 < median - 15.0, (gray.std(), p2, median)
    return {"inner": inner_cov, "outer": outer_cov, "std": float(gray.std()), "median": median, "p2": p2}


def open_viewer(browser: Any, url: str) -> tuple[Any, list[str]]:
    """Open the viewer page; return (page, problems: failed requests and page errors)."""
    page = browser.new_page(viewport={"width": 1100, "height": 800})
    problems: list[str] = []
    page.on("pageerror", lambda e: problems.append(f"pageerror: {e}"))
    page.on("response", lambda r: problems.append(f"{r.status} {r.url.split('?')[0]}") if r.status >= 400 else None)
    page.goto(url)
    return page, problems


def test_viewer_live_in_chromium(service: Service, scan: Scan) -> None:
    from playwright.sync_api import sync_playwright

    client = VeinmosaicClient(service.base_url, KEY)
    created = client.create_session(scan.calibration.to_dict(), "Jane Doe 1970")
    sid = created["id"]
    viewer_url = f"{service.base_url}{created['viewer_url']}"

    def mosaic_version() -> int:
        return int(client.request("GET", f"/v1/sessions/{sid}/mosaic.json").json()["version"])

    def shows(page: Any, version: int) -> bool:
        return bool(
            page.evaluate(
                "(version) => { const v = window.veinmosaicViewer; return v && v.state.mosaicVersion >= version"
                " && v.idle(); }",
                version,
            )
        )

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            # one page opened before any upload (it starts from nothing and follows the events) ...
            early, early_problems = open_viewer(browser, viewer_url)
            assert "Jane Doe" not in early.content()
            upload_frames(client, sid, scan, range(FIRST_PART))
            wait_until(lambda: client.session(sid)["frames_processed"] >= FIRST_PART, "the first part processed")
            # ... and one opened after part of the scan was processed (it starts from the snapshot)
            page, problems = open_viewer(browser, viewer_url)
            for p in (early, page):
                wait_until(lambda p=p: shows(p, mosaic_version()), "the viewer to show the current mosaic")
            page.wait_for_timeout(800)  # let the fit animation settle
            early.wait_for_timeout(10)
            rows = client.request("GET", f"/v1/sessions/{sid}/path").json()
            doc = client.request("GET", f"/v1/sessions/{sid}/mosaic.json").json()
            ok = [r for r in rows if r["status"] == "ok"]
            assert len(rows) == FIRST_PART and len(ok) >= FIRST_PART - 2
            radius = doc["extent_mm"][2] - max(r["x_mm"] for r in ok)  # extent = centres +- window radius
            first = CanvasView(page.evaluate(CANVAS_JS))
            check_matches_path(first, rows, radius)
            check_matches_path(CanvasView(early.evaluate(CANVAS_JS)), rows, radius)
            assert first.doc["polyline"] == len(ok)  # the probe path overlay has a point per placed frame
            status_text = page.inner_text("#status")
            assert f"{len(rows)} frames processed" in status_text, status_text
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "viewer_partial.png"))

            upload_frames(client, sid, scan, range(FIRST_PART, len(scan)))
            client.finish(sid)
            for p in (early, page):
                wait_until(lambda p=p: p.evaluate("() => window.veinmosaicViewer.state.done"), "the done event")
                wait_until(lambda p=p: shows(p, mosaic_version()), "the viewer to show the final mosaic")
            page.wait_for_timeout(800)
            rows = client.request("GET", f"/v1/sessions/{sid}/path").json()
            final = CanvasView(page.evaluate(CANVAS_JS))
            ok = [r for r in rows if r["status"] == "ok"]
            assert len(rows) == len(scan)
            doc = client.request("GET", f"/v1/sessions/{sid}/mosaic.json").json()
            check_matches_path(final, rows, doc["extent_mm"][2] - max(r["x_mm"] for r in ok))
            # the whole scan covers more skin than its first part (areas in mm^2, independent of zoom)
            assert final.covered_area_mm2() > 1.15 * first.covered_area_mm2()
            assert not np.array_equal(final.bgra, first.bgra)
            assert "done" in page.inner_text("#status")
            page.screenshot(path=str(ARTIFACTS / "viewer.png"))

            page.check('input[name="layer"][value="force"]')
            wait_until(lambda: page.evaluate("() => window.veinmosaicViewer.idle()"), "the force layer")
            page.wait_for_timeout(300)
            force = CanvasView(page.evaluate(CANVAS_JS))
            bgr = force.bgra[..., :3].astype(int)[force.covered()]
            chroma = np.abs(bgr[:, 0] - bgr[:, 2])
            assert np.median(chroma) > 30  # the force layer is colour-coded, not gray
            page.screenshot(path=str(ARTIFACTS / "viewer_force.png"))
            assert not problems and not early_problems, problems + early_problems
        finally:
            with contextlib.suppress(Exception):
                browser.close()
    client.close()


def test_reference_and_reprocess_end_to_end(service: Service, scan: Scan) -> None:
    """A whole scan through the real service, then reference.csv, a reprocess job and the new version."""
    client = VeinmosaicClient(service.base_url, KEY)
    sid = client.create_session(scan.calibration.to_dict(), "")["id"]
    upload_frames(client, sid, scan, range(len(scan)))
    client.finish(sid)
    assert client.wait_done(sid, timeout_s=WAIT_S)["status"] == "done"
    truth = np.asarray(scan.truth["poses"], float)
    reference = "seq,x_mm,y_mm\n" + "".join(f"{i},{x:.6f},{y:.6f}\n" for i, (x, y, _) in enumerate(truth))
    report = client.post_reference(sid, reference)
    assert report["n_compared"] == len(scan) and report["rmse_mm"] < 2.0  # the short scan: about 1 mm or better
    assert client.request("GET", report["plots"]["paths"]).content.startswith(b"\x89PNG")

    job = client.request("POST", f"/v1/sessions/{sid}/reprocess", json={"options": {"method": "sift-chain"}}).json()
    state = wait_until(
        lambda: (s := client.request("GET", f"/v1/jobs/{job['job']}").json())["status"] in ("done", "failed") and s,
        "the reprocess job",
    )
    assert state["state"] == "done" and state["version"] == 2 and state["progress"] == 1.0, state
    doc = client.request("GET", f"/v1/sessions/{sid}/mosaic.json").json()
    assert doc["results_version"] == 2
    v2 = client.request("GET", f"/v1/sessions/{sid}/report").json()  # evaluated by the worker for version 2
    assert v2["results_version"] == 2 and v2["n_frames"] == len(scan)
    v1 = client.request("GET", f"/v1/sessions/{sid}/report?v=1").json()
    assert v1["rmse_mm"] == report["rmse_mm"]
    client.close()
