"""Writing a reconstruction (spec §4) to an output folder: path.csv, mosaic, layers, report (the path row's CSV and
JSON forms themselves: tests/services/core/test_path_rows.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.core.mosaic.canvas import MosaicImage
from services.core.pipeline import Reconstruction
from services.core.similarity import IDENTITY, Similarity
from services.store.output_folder import read_results_mosaic, write_reconstruction
from tests.services.core.test_path_rows import three_rows as _rows

NAN = math.nan


def _recon() -> Reconstruction:
    vein = np.zeros((60, 80), np.uint8)
    vein[10:50, 10:70] = 200
    force = np.full((60, 80), np.nan, np.float32)
    force[10:50, 10:70] = 12.0
    mosaic = MosaicImage(vein, force, (vein > 0).astype(np.float32), 8.0, (20.0, 30.0))
    poses = {0: IDENTITY, 2: Similarity(1 + 0j, 1.23456 - 2.5j)}
    return Reconstruction("best", _rows(), poses, mosaic, None, 1.5)


def test_write_reconstruction_without_reference(tmp_path: Path) -> None:
    report = write_reconstruction(_recon(), tmp_path / "out", None)
    assert report.accuracy is None
    out = tmp_path / "out"
    assert {p.name for p in out.iterdir()} == {
        "path.csv", "mosaic.png", "force.png", "coverage.png", "layers.npz", "mosaic.json", "force_map.png",
        "coverage_map.png", "report.json", "sheet.png", "sheet.pdf",
    }  # fmt: skip
    png = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint8 and png.shape == (60, 80)
    meta = json.loads((out / "mosaic.json").read_text())
    assert meta["px_per_mm"] == 8.0 and meta["origin_px"] == [20.0, 30.0]
    assert (meta["width"], meta["height"]) == (80, 60)
    assert meta["method"] == "best"
    force = cv2.imread(str(out / "force.png"), cv2.IMREAD_UNCHANGED)
    assert force.shape == (60, 80, 3)  # the layer, pixel-aligned with mosaic.png
    assert force[0, 0].tolist() == [0, 0, 0] and force[30, 40].sum() > 0
    coverage = cv2.imread(str(out / "coverage.png"), cv2.IMREAD_UNCHANGED)
    assert coverage.shape == (60, 80, 4)  # BGRA: transparent where never scanned
    assert coverage[0, 0, 3] == 0 and coverage[30, 40, 3] == 255
    # the raw layers read back in N and frames
    back = read_results_mosaic(out)
    assert np.nanmax(back.force_n) == pytest.approx(12.0, abs=0.005) and np.isnan(back.force_n[0, 0])
    assert back.coverage[30, 40] == 1 and back.coverage[0, 0] == 0
    # report.json without a reference: the frames and the warning, no accuracy figures
    doc = json.loads((out / "report.json").read_text())
    assert "rmse_mm" not in doc
    assert doc["frames"] == {
        "total": 3, "ok": 2, "lost": 1, "rejected": 0, "no_contact": 0, "registered_fraction": pytest.approx(2 / 3),
        "lost_reasons": {"few_inliers": 1}, "rejected_reasons": {}, "keyframes": 2, "tracked": 0,
        "stitched": 2,
    }  # fmt: skip
    assert [w["code"] for w in doc["warnings"]] == ["frames_lost"]  # 1 of 3 > 5 %
    assert (out / "sheet.pdf").read_bytes().startswith(b"%PDF")
    for name in ("force_map.png", "coverage_map.png", "sheet.png"):
        assert cv2.imread(str(out / name)) is not None


def test_write_reconstruction_with_reference(tmp_path: Path) -> None:
    reference = np.array([[0.0, 0.0], [0.5, -1.0], [1.23456 + 0.3, -2.5 - 0.4]])  # frame 2 off by 0.5 mm
    report = write_reconstruction(_recon(), tmp_path, reference, sheet=False)
    assert report.accuracy is not None
    doc = json.loads((tmp_path / "report.json").read_text())
    # errors 0 and 0.5 mm over the two registered frames: RMSE sqrt(0.25 / 2)
    assert doc["rmse_mm"] == pytest.approx(math.sqrt(0.125), rel=1e-9)
    assert doc["registered_fraction"] == pytest.approx(2 / 3)
    assert doc["method"] == "best" and doc["seconds_per_frame"] == pytest.approx(0.5)
    assert doc["plots"] == {"paths": "paths.png", "errors": "errors.png"}
    assert "2/3 frames registered" in doc["accuracy_summary"]
    for name in ("paths.png", "errors.png"):
        assert cv2.imread(str(tmp_path / name)) is not None
