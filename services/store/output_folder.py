"""Writing a reconstruction to an output folder (spec §4).

OUTPUTS: path.csv; mosaic.png (8-bit veins) and mosaic.json; force.png and coverage.png (the layers, pixel-
aligned with mosaic.png: TURBO over 0..30 N; VIRIDIS over 1..10 frames with alpha 0 where never scanned);
layers.npz (force in cN, coverage counts: for the DICOM export, whose UIDs derive from mosaic.json's
scan_digest); force_map.png and coverage_map.png (the layers in mm with their colour scales); report.json
(frames per status and reason, warnings, accuracy with a reference); with a reference paths.png and
errors.png; sheet.png and sheet.pdf (the one-page report).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from services.core.mosaic.canvas import MosaicImage
from services.core.mosaic.layer_images import layers_from_bytes, mosaic_image_files
from services.core.outputs.documents import folder_mosaic_json
from services.core.outputs.plots import plot_coverage_map, plot_force_map
from services.core.outputs.session_report import SessionReport, build_session_report
from services.core.outputs.sheet import SheetIdentity
from services.core.path_rows import path_csv
from services.core.pipeline import Reconstruction


def write_reconstruction(
    recon: Reconstruction,
    out_dir: str | Path,
    reference: np.ndarray | None,
    sheet: bool = True,
    scan_digest: str | None = None,
    label: str | None = None,
) -> SessionReport:
    """Write every output of a reconstruction to out_dir (see OUTPUTS); return its SessionReport.

    reference: the (N, 2) or (N, 5) reference track (services.core.outputs.session_report.build_session_report).
    scan_digest: the scan's content digest (services.core.outputs.dicom_export.scan_digest), recorded in mosaic.json:
    the key the DICOM export's UIDs derive from.
    label: what the one-page report names the scan by (e.g. the scan folder's name; default: out_dir's name).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "path.csv").write_text(path_csv(recon.rows))
    mosaic = recon.mosaic
    for name, data in mosaic_image_files(mosaic).items():
        (out / name).write_bytes(data)
    (out / "force_map.png").write_bytes(plot_force_map(mosaic.force_n, mosaic.px_per_mm, mosaic.origin_px))
    (out / "coverage_map.png").write_bytes(plot_coverage_map(mosaic.coverage, mosaic.px_per_mm, mosaic.origin_px))
    meta = folder_mosaic_json(
        mosaic.meta(), method=recon.method, compliance=recon.compliance, tissue=recon.learned, scan_digest=scan_digest
    )
    (out / "mosaic.json").write_text(json.dumps(meta, indent=2))
    extra = {
        "method": recon.method,
        "seconds_per_frame": recon.seconds / max(1, len(recon.rows)),
        "tissue": recon.learned,
    }
    identity = SheetIdentity(session=label or out.resolve().name, method=recon.method)  # offline: no patient
    report = build_session_report(
        recon.rows,
        reference,
        mosaic,
        extra,
        identity=identity,
        sheet=sheet,
        placed=recon.placed,
    )
    for name, data in report.images.items():
        (out / name).write_bytes(data)
    (out / "report.json").write_text(json.dumps(report.doc, indent=2, allow_nan=False))
    return report


def read_results_mosaic(out_dir: str | Path) -> MosaicImage:
    """Return the mosaic (vein, force in N, coverage, geometry) of a folder written by write_reconstruction."""
    out = Path(out_dir)
    vein = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_GRAYSCALE)
    if vein is None or not (out / "layers.npz").is_file():
        raise ValueError(f"{out}: not a reconstruction output folder (mosaic.png and layers.npz expected)")
    return layers_from_bytes((out / "layers.npz").read_bytes(), vein)
