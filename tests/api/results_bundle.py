"""A results bundle made with the workers' services code (SessionReconstruction live + TilePyramid) on a simulated
scan, and its installation with ResultsStore: what the results and report route tests serve (test_results.py,
test_report.py; the fixtures short_scan, bundle and ready are in tests/api/conftest.py)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from api_helpers import INGEST
from fastapi.testclient import TestClient

from services.core.inputs.scan import Scan
from services.core.methods import method_options
from services.core.mosaic.canvas import force_to_color
from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
from services.core.path_rows import PathRow, path_rows_json
from services.core.pipeline import frame_forces, prepared_frames, window_radius_mm, window_setup
from services.core.session_reconstruction import SessionReconstruction
from services.store.results_store import LAYERS, ResultsStore


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


def png(img: np.ndarray) -> bytes:
    """Return `img` encoded as PNG."""
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
            tile_png = pyramid.render_png(level, col, row, layer)
            if tile_png is not None:
                tiles[(layer, level, col, row)] = tile_png
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
        "frames": {
            "processed": len(rows),
            "ok": len(ok),
            "lost": 0,
            "rejected": 0,
            "no_contact": 0,
            "in_fragments": 0,
            "keyframes": len(ok),
            "tracked": 0,
            "stitched": len(ok),
        },
        "status": "done" if final else "processing",
    }
    truth = np.asarray(scan.truth["poses"], float)[:n, :2]
    return Bundle(rows, tiles, doc, png(mosaic.vein), png(force_to_color(mosaic.force_n)), truth)


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


def create_session(client: TestClient, scan: Scan, key: dict[str, str] = INGEST) -> dict[str, Any]:
    """Create a session with the scan's calibration; return the 201 body."""
    resp = client.post(
        "/v1/sessions", json={"calibration": scan.calibration.to_dict(), "label": "Jane Doe 1970"}, headers=key
    )
    assert resp.status_code == 201, resp.text
    return resp.json()
