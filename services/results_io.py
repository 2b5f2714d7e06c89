"""Writing a reconstruction to an output folder (spec §4): path.csv, mosaic.png/json, force.png, report."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.evaluation import AccuracyReport, evaluate_path
from services.mosaic import force_to_color
from services.pipeline import PATH_COLUMNS, PathRow, Reconstruction
from services.plots import plot_error_along_scan, plot_paths_over_mosaic


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return "" if not math.isfinite(value) else f"{value:.4f}"
    return str(value)


def path_csv(rows: list[PathRow]) -> str:
    """Return the path as CSV text (spec §4 columns; empty cells where a frame was not registered)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(PATH_COLUMNS)
    for r in rows:
        writer.writerow([_cell(getattr(r, c)) for c in PATH_COLUMNS])
    return out.getvalue()


def write_reconstruction(
    recon: Reconstruction, out_dir: str | Path, reference_mm: np.ndarray | None
) -> AccuracyReport | None:
    """Write every output of a reconstruction to out_dir; return the accuracy report when there is a reference."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "path.csv").write_text(path_csv(recon.rows))
    mosaic = recon.mosaic
    cv2.imwrite(str(out / "mosaic.png"), mosaic.vein)
    cv2.imwrite(str(out / "force.png"), force_to_color(mosaic.force_n))
    # coverage: how many frames saw each point (8-bit count, saturating at 255)
    cv2.imwrite(str(out / "coverage.png"), np.clip(np.rint(mosaic.coverage), 0, 255).astype(np.uint8))
    meta = mosaic.meta()
    meta["method"] = recon.method
    if recon.compliance is not None:
        meta["compliance_per_n"] = recon.compliance.compliance_per_n
        meta["gauge"] = recon.compliance.gauge
    (out / "mosaic.json").write_text(json.dumps(meta, indent=2))
    if reference_mm is None:
        return None
    report = evaluate_path(recon.estimate_mm, recon.registered, reference_mm)
    doc = report.to_dict()
    doc["method"] = recon.method
    doc["seconds_per_frame"] = recon.seconds / max(1, len(recon.rows))
    doc["plots"] = {"paths": "paths.png", "errors": "errors.png"}
    (out / "report.json").write_text(json.dumps(doc, indent=2))
    plot_paths_over_mosaic(
        out / "paths.png",
        recon.estimate_mm,
        recon.registered,
        reference_mm,
        mosaic.vein,
        mosaic.px_per_mm,
        mosaic.origin_px,
    )
    plot_error_along_scan(out / "errors.png", report)
    return report
