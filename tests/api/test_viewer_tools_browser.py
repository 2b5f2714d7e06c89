"""The viewer's clinical tools in a real headless Chromium against the real API (HTTP, Redis, no workers).

The results are a known fixture written with the services code the workers use (SparseCanvas, TilePyramid,
ResultsStore): 30 synthetic frames placed along a straight 58 mm line, 5 of them lost — independent of the
registration algorithm, so the viewer is tested on geometry known exactly; 6 of the placed count as tracked (placed
without features). Checked for real in the page: the status line counts the tracked frames, the mm scale bar follows
the zoom, the measuring tool reads the known distance between the path's start and
end in mm, the banner shows the >5 % lost warning, lost frames are marked, hovering a frame shows its seq,
time and load in N, and the coverage layer renders in colour where the vein layer is grey.
Screenshots go to tests/artifacts/viewer_tools_*.png.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from browser_service import ARTIFACTS, CHROMIUM, CHROMIUM_ARGS, browser_service

from cli.client import VeinmosaicClient
from cli.launcher import Service
from services.core.mosaic.canvas import FrameLayers, SparseCanvas, blend_weight
from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
from services.core.outputs.documents import LAYERS, canvas_extent_mm, empty_revisions, mosaic_json
from services.core.path_rows import PathRow, PlacedCounts
from services.core.similarity import Similarity
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore
from services.store.version_state import VersionState

pytestmark = pytest.mark.slow

KEY = "viewer-tools-key-0123456789abcdef"
PX_PER_MM = 8.0
N_FRAMES = 30
STEP_MM = 2.0
LOST = (7, 8, 15, 21, 22)  # not placed: 5 of 30 = 16.7 % > 5 %, the banner must show
REJECTED = (22,)  # of those, rejected (blur) rather than lost
TRACKED = 6  # placed frames tracked without features (a live session behind its uploads): the status line says so
FRAME_SHAPE = (160, 200)  # h, w px: 20 x 25 mm


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """Start Redis (REDIS_URL, else embedded) and the API on a free port, without workers."""
    with browser_service(tmp_path_factory.mktemp("tools") / "data", KEY, workers=0) as svc:
        yield svc


def _frame(seq: int) -> FrameLayers:
    rng = np.random.default_rng(seq)
    h, w = FRAME_SHAPE
    veins = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 6)
    veins = (veins - veins.min()) / (np.ptp(veins) + 1e-6)
    mask = np.zeros((h, w), np.uint8)
    cv2.ellipse(mask, (w // 2, h // 2), (w // 2 - 4, h // 2 - 4), 0, 0, 360, 255, -1)
    weight = blend_weight(mask, ramp_px=10)
    force = np.full((h, w), 4.0 + 0.5 * seq, np.float32)
    return FrameLayers.of(0.3 + 0.4 * veins, weight, force, (w / 2, h / 2), PX_PER_MM)


def install_fixture(data_dir: Path, sid: str) -> list[PathRow]:
    """Write results version 1 of `sid` as a worker would: tiles, images, mosaic.json, path, state."""
    canvas = SparseCanvas(PX_PER_MM)
    rows = []
    for seq in range(N_FRAMES):
        x = STEP_MM * seq
        lost = seq in LOST
        status = "rejected" if seq in REJECTED else "lost" if lost else "ok"
        reason = "blur" if seq in REJECTED else "few_inliers" if lost else ""
        if not lost:
            canvas.paste(_frame(seq), Similarity(1 + 0j, complex(x, 0.0)))
        nan = float("nan")
        rows.append(
            PathRow(
                seq, 0.1 * seq, nan if lost else x, nan if lost else 0.0, nan if lost else 0.0, 4.0 + 0.5 * seq,
                0.0, 0.0, 1.0, 0 if lost else 120, status, reason,
            )
        )  # fmt: skip
    lost_seqs = [s for s in LOST if s not in REJECTED]
    doc = _write_results(data_dir, sid, canvas, rows, lost=lost_seqs, rejected=REJECTED, tracked=TRACKED)
    assert doc["frames"] == {
        "processed": N_FRAMES, "ok": N_FRAMES - len(LOST), "lost": 4, "rejected": 1, "no_contact": 0, "in_fragments": 0,
        "keyframes": N_FRAMES - len(LOST) - TRACKED, "tracked": TRACKED, "stitched": N_FRAMES - len(LOST),
    }  # fmt: skip
    return rows


def _write_results(
    data_dir: Path,
    sid: str,
    canvas: SparseCanvas,
    rows: list[PathRow],
    lost: list[int],
    rejected: tuple[int, ...],
    tracked: int = 0,
) -> dict[str, Any]:
    """Write results version 1 of `sid` as a worker would (tiles, images, mosaic.json, path, state); return
    mosaic.json (tracked: how many placed frames it counts as tracked)."""
    rs = ResultsStore(data_dir)
    rs.ensure_version(sid, 1, {"method": "best"})
    geometry = DziGeometry.for_mosaic(PX_PER_MM)
    pyramid = TilePyramid(geometry)
    revisions = empty_revisions()
    for level, col, row in pyramid.update(canvas, set(canvas.tiles)):
        for layer in LAYERS:
            png = pyramid.render_png(level, col, row, layer)
            if png is not None:
                rs.write_tile(sid, 1, layer, level, col, row, png)
                revisions[layer][f"{level}/{col}_{row}"] = 1
    mosaic = canvas.render()
    rs.write_mosaic_images(sid, 1, mosaic)
    doc = mosaic_json(
        mosaic.meta(),
        version=1,
        results_version=1,
        revisions=revisions,
        geometry=geometry,
        extent_mm=canvas_extent_mm(canvas),
        rows=rows,
        status="done",
        method="best",
        placed=PlacedCounts(tracked=tracked),
    )
    rs.write_mosaic_meta(sid, 1, doc)
    rs.write_path(sid, 1, rows)
    state = VersionState(cursor=len(rows), fence=1, finished=True, lost=list(lost), rejected=list(rejected))
    rs.write_state(sid, 1, state)
    return doc


def install_strokes_fixture(data_dir: Path, sid: str) -> list[PathRow]:
    """Write a scan in two strokes: frames 0-9 along y = 0, five frames in the air, frames 15-24 along y = 12."""
    canvas = SparseCanvas(PX_PER_MM)
    rows, nan = [], float("nan")
    for seq in range(25):
        air = 10 <= seq < 15
        stroke = None if air else int(seq >= 15)
        x, y = STEP_MM * (seq % 15), 12.0 * (seq >= 15)
        if not air:
            canvas.paste(_frame(seq), Similarity(1 + 0j, complex(x, y)))
        rows.append(
            PathRow(
                seq, 0.1 * seq, nan if air else x, nan if air else y, nan if air else 0.0, 0.05 if air else 6.0,
                0.0, 0.0, 1.0, 0 if air else 120, "rejected" if air else "ok", "no_contact" if air else "", stroke,
            )
        )  # fmt: skip
    _write_results(data_dir, sid, canvas, rows, lost=[], rejected=tuple(range(10, 15)))
    return rows


STATUS_LOG_JS = """
window.__statusLog = [];
document.addEventListener("DOMContentLoaded", () => {
  const el = document.getElementById("status");
  const note = () => window.__statusLog.push(el.textContent);
  note();
  new MutationObserver(note).observe(el, { childList: true, characterData: true, subtree: true });
});
"""


def _element_xy(page: Any, x_mm: float, y_mm: float) -> tuple[float, float]:
    """Return the page coordinates of a mosaic point (mm), computed by OpenSeadragon, not by viewer.js."""
    return tuple(
        page.evaluate(
            """([x, y]) => {
              const v = window.veinmosaicViewer, d = v.state.dzi;
              const item = v.currentItem();
              const p = item.imageToViewerElementCoordinates(
                new OpenSeadragon.Point(d.origin_px[0] + x * v.state.pxPerMm, d.origin_px[1] + y * v.state.pxPerMm));
              const box = v.viewer.element.getBoundingClientRect();
              return [box.left + p.x, box.top + p.y];
            }""",
            [x_mm, y_mm],
        )
    )


def _screen_px_per_mm(page: Any) -> float:
    return float(
        page.evaluate(
            """() => {
              const v = window.veinmosaicViewer, item = v.currentItem();
              const a = item.imageToViewerElementCoordinates(new OpenSeadragon.Point(0, 0));
              const b = item.imageToViewerElementCoordinates(new OpenSeadragon.Point(v.state.pxPerMm, 0));
              return b.x - a.x;
            }"""
        )
    )


def _wait_idle(page: Any) -> None:
    page.wait_for_function("() => window.veinmosaicViewer && window.veinmosaicViewer.idle()", timeout=30000)
    page.wait_for_timeout(700)  # the viewport animation (0.5 s) settles


def _pixel(shot: np.ndarray, xy: tuple[float, float], box: dict[str, float]) -> np.ndarray:
    x, y = round(xy[0] - box["x"]), round(xy[1] - box["y"])
    return shot[y - 2 : y + 3, x - 2 : x + 3].reshape(-1, 3).astype(int)


def done_session(
    service: Service, install: Callable[[Path, str], list[PathRow]]
) -> tuple[VeinmosaicClient, dict[str, Any]]:
    """Return a client and a new session (its create answer) whose results `install` wrote, finished and done."""
    client = VeinmosaicClient(service.base_url, KEY)
    calibration = {"image_size": [200, 160], "camera_matrix": [[300, 0, 100], [0, 300, 80], [0, 0, 1]]}
    created = client.create_session({**calibration, "px_per_mm": PX_PER_MM}, "")
    install(service.data_dir, created["id"])
    store = SessionStore(service.data_dir)
    store.finish(created["id"])
    store.set_status(created["id"], "done")  # as the register stage does when the version is complete
    return client, created


def test_viewer_tools_in_chromium(service: Service) -> None:
    from playwright.sync_api import sync_playwright

    client, created = done_session(service, install_fixture)
    sid = created["id"]
    store = SessionStore(service.data_dir)
    state = client.session(sid)
    assert [w["code"] for w in state["warnings"]] == ["frames_lost"], state
    assert state["not_placed_reasons"] == {"few_inliers": len(LOST) - len(REJECTED), "blur": len(REJECTED)}
    ARTIFACTS.mkdir(parents=True, exist_ok=True)

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 800})
            page.add_init_script(STATUS_LOG_JS)  # every text the status line shows, from the first paint
            problems: list[str] = []
            page.on("pageerror", lambda e: problems.append(f"pageerror: {e}"))
            page.on("response", lambda r: problems.append(f"{r.status} {r.url}") if r.status >= 400 else None)
            page.goto(f"{service.base_url}{created['viewer_url']}")
            _wait_idle(page)
            # the session is done before the page opens: while its results load the status line must not
            # read "done · 0 frames processed"
            shown = page.evaluate("() => window.__statusLog")
            assert shown and not any("· 0 frames processed" in t for t in shown), shown

            # banner: the >5 % rule, with the reason
            page.wait_for_selector("#banner:not([hidden])", timeout=15000)
            banner = page.inner_text("#banner")
            assert "5 of 30 frames" in banner and "few inliers 4" in banner and "blur 1" in banner, banner
            status = page.inner_text("#status")
            counts = "done · 30 frames processed (25 placed, 6 of them tracked, 4 lost, 1 rejected)"
            assert status.startswith(counts), status

            # start and end markers, lost frames marked
            assert page.get_attribute("#path-overlay circle.start", "visibility") == "visible"
            assert page.get_attribute("#path-overlay rect.end", "visibility") == "visible"
            assert page.locator("#path-overlay path.lost").count() == len(LOST)  # every frame not placed
            assert page.locator("#path-overlay path.lost.rejected").count() == len(REJECTED)  # rejected told apart

            # the scale bar: its length in px is its label in mm at the screen's scale, and it follows the zoom
            def scale() -> tuple[str, float, float]:
                text = page.inner_text("#scale-bar .label")
                bar_px = page.evaluate("() => document.querySelector('#scale-bar .bar').getBoundingClientRect().width")
                return text, float(bar_px), _screen_px_per_mm(page)

            text1, bar1, ppm1 = scale()
            mm1 = float(text1.split()[0])
            assert bar1 == pytest.approx(mm1 * ppm1, rel=0.03), (text1, bar1, ppm1)
            page.screenshot(path=str(ARTIFACTS / "viewer_tools_overview.png"))
            page.evaluate("() => window.veinmosaicViewer.viewer.viewport.zoomBy(6, undefined, true)")
            page.wait_for_timeout(700)
            text2, bar2, ppm2 = scale()
            assert ppm2 == pytest.approx(6 * ppm1, rel=0.05)
            assert text2 != text1 and float(text2.split()[0]) < mm1, (text1, text2)
            assert bar2 == pytest.approx(float(text2.split()[0]) * ppm2, rel=0.03)
            page.click("#fit")
            page.wait_for_timeout(900)

            # measuring: click the start and the end frames' centres: 29 * 2 = 58 mm apart
            page.click("#measure")
            start = _element_xy(page, 0.0, 0.0)
            end = _element_xy(page, STEP_MM * (N_FRAMES - 1), 0.0)
            page.mouse.click(*start)
            page.wait_for_timeout(300)
            page.mouse.click(*end)
            page.wait_for_function("() => window.veinmosaicViewer.state.measure.mm !== null")
            measured = float(page.evaluate("() => window.veinmosaicViewer.state.measure.mm"))
            # the two recorded points are where the clicks landed, and the view did not move under them
            for clicked, (x_px, y_px) in zip(
                (start, end), page.evaluate("() => window.veinmosaicViewer.state.measure.points"), strict=True
            ):
                doc = page.evaluate("() => window.veinmosaicViewer.state.dzi.origin_px")
                mm = ((x_px - doc[0]) / PX_PER_MM, (y_px - doc[1]) / PX_PER_MM)
                now = _element_xy(page, *mm)
                assert now == pytest.approx(clicked, abs=1.5), (now, clicked)
            half_px_mm = 1.0 / _screen_px_per_mm(page)  # a click lands on a whole screen pixel
            assert measured == pytest.approx(STEP_MM * (N_FRAMES - 1), abs=2 * half_px_mm + 0.05)
            assert f"{measured:.1f} mm" == page.text_content("#measure-label")
            assert "distance" in page.inner_text("#status")
            page.screenshot(path=str(ARTIFACTS / "viewer_tools_measure.png"))
            page.click("#measure")

            # hovering a frame of the path: seq, time, load in N, status
            page.mouse.move(*_element_xy(page, STEP_MM * 4, 0.0))
            page.wait_for_selector("#tooltip:not([hidden])", timeout=5000)
            tip = page.inner_text("#tooltip")
            assert tip.startswith("frame 4") and "t 0.40 s" in tip and "load 6.0 N" in tip and "ok" in tip, tip
            page.mouse.move(*_element_xy(page, STEP_MM * 15, 0.0))  # a lost frame, marked between its neighbours
            page.wait_for_function("() => document.querySelector('#tooltip').textContent.startsWith('frame 15')")
            assert "lost (few inliers)" in page.inner_text("#tooltip")
            page.mouse.move(*_element_xy(page, STEP_MM * 22, 0.0))  # the rejected frame
            page.wait_for_function("() => document.querySelector('#tooltip').textContent.startsWith('frame 22')")
            assert "rejected (blur)" in page.inner_text("#tooltip")
            page.mouse.move(5, 5)

            # coverage layer: colour where the vein layer is grey, with its legend
            probe = _element_xy(page, STEP_MM * 12, 6.0)  # off the drawn path
            box = page.locator("#viewer").bounding_box()
            vein = cv2.imdecode(np.frombuffer(page.locator("#viewer").screenshot(), np.uint8), cv2.IMREAD_COLOR)
            page.check('input[name="layer"][value="coverage"]')
            page.wait_for_function("() => window.veinmosaicViewer.state.layer === 'coverage'")
            _wait_idle(page)
            assert page.is_visible("#coverage-legend") and not page.is_visible("#force-legend")
            shot = page.locator("#viewer").screenshot()
            (ARTIFACTS / "viewer_tools_coverage.png").write_bytes(shot)
            cov = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
            vein_px, cov_px = _pixel(vein, probe, box), _pixel(cov, probe, box)
            assert np.ptp(vein_px, axis=1).max() <= 6, vein_px  # grey veins
            assert np.ptp(cov_px, axis=1).min() >= 40, cov_px  # a colour of the VIRIDIS scale
            page.check('input[name="layer"][value="force"]')
            _wait_idle(page)
            legend = page.inner_text("#force-legend")
            assert "0 N" in legend and "30 N" in legend, legend  # the force scale in N
            assert not problems, problems

            # the banner also tells of a reprocess running and of a failed processing
            ResultsStore(service.data_dir).create_version(sid, {"method": "best"}, make_current=False)
            assert "reprocess_running" in [w["code"] for w in client.session(sid)["warnings"]]
            page.goto(f"{service.base_url}{created['viewer_url']}")  # the link again: the page's URL has no token
            page.wait_for_function("() => document.querySelector('#banner').textContent.includes('reprocess')")
            assert not page.is_hidden("#banner") and "5 of 30 frames" in page.inner_text("#banner")
            store.set_status(sid, "failed")
            page.goto(f"{service.base_url}{created['viewer_url']}")
            page.wait_for_function("() => document.querySelector('#banner').textContent.includes('failed')")
            assert "Processing failed" in page.inner_text("#banner")
            page.screenshot(path=str(ARTIFACTS / "viewer_tools_banner.png"))
        finally:
            browser.close()


def test_strokes_are_drawn_apart_and_frames_in_the_air_are_not_marked_lost(service: Service) -> None:
    from playwright.sync_api import sync_playwright

    client, created = done_session(service, install_strokes_fixture)
    sid = created["id"]
    assert client.session(sid)["warnings"] == []  # frames in the air are not frames lost
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 800})
            page.goto(f"{service.base_url}{created['viewer_url']}")
            _wait_idle(page)
            page.wait_for_function("() => document.querySelectorAll('#path-overlay polyline').length === 2")
            points = page.evaluate(
                """() => Array.from(document.querySelectorAll('#path-overlay polyline'))
                     .map((l) => l.getAttribute('points').split(' ').filter(Boolean).length)"""
            )
            assert sorted(points) == [10, 10]  # one line per stroke, none through the air between them
            assert page.locator("#path-overlay path.lost").count() == 0  # the air's frames are no lost crosses
            status = page.inner_text("#status")
            assert "20 placed" in status and "5 off the skin" in status and "rejected" not in status, status
            page.screenshot(path=str(ARTIFACTS / "viewer_tools_strokes.png"))
        finally:
            browser.close()


def test_the_token_leaves_the_address_bar_and_tiles_still_load(service: Service) -> None:
    """The viewer link's ?token= is gone from the URL and the history once the page has read it, and the page
    still loads its tiles, DZI geometry and event stream with it (kept in memory), before and after a layer change."""
    from playwright.sync_api import sync_playwright

    _client, created = done_session(service, install_fixture)
    token = created["viewer_token"]
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 800})
            answers: list[tuple[int, str]] = []
            page.on("response", lambda r: answers.append((r.status, r.url)))
            page.goto(f"{service.base_url}{created['viewer_url']}")
            _wait_idle(page)
            assert token not in page.url and "token" not in page.url, page.url
            assert page.url == f"{service.base_url}/viewer/{created['id']}"
            assert token not in page.evaluate("() => window.location.href + JSON.stringify(window.history.state)")

            def loaded(kind: str) -> list[str]:
                return [url for status, url in answers if status == 200 and kind in url]

            assert loaded("/mosaic_files/") and loaded("/mosaic.json") and loaded("/events"), answers
            assert not [a for a in answers if a[0] >= 400], answers
            # tiles asked for after the URL lost the token still carry it (from memory) and load
            before = len(loaded("layer=force"))
            page.check('input[name="layer"][value="force"]')
            _wait_idle(page)
            assert len(loaded("layer=force")) > before and not [a for a in answers if a[0] >= 400], answers
            assert page.evaluate("() => window.veinmosaicViewer.currentItem().getFullyLoaded()")
            assert "token" not in page.url
            page.go_back()  # the entry was replaced, not pushed: no entry behind it holds the token
            assert page.url == "about:blank", page.url
        finally:
            browser.close()
