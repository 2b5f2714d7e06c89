"""The two mosaic.json documents (services/core/outputs/documents.py): the folder's and the service's share parts."""

from __future__ import annotations

import json

import numpy as np

from services.core.mosaic.canvas import MosaicImage
from services.core.mosaic.deepzoom import DziGeometry
from services.core.outputs.documents import empty_revisions, folder_mosaic_json, mosaic_json
from services.core.physics.compliance import ComplianceFit

IMAGE = MosaicImage(
    vein=np.zeros((60, 80), np.uint8),
    force_n=np.full((60, 80), np.nan, np.float32),
    coverage=np.zeros((60, 80), np.uint16),
    px_per_mm=8.0,
    origin_px=(20.0, 30.0),
).meta()
FIT = ComplianceFit(compliance_per_n=0.006, gauge=1.002, residual_rms=0.001, n_frames=40)
TISSUE = {"kappa_n_per_mm": 0.15}


def test_the_folders_mosaic_json_is_the_spec_image_part_with_the_fit_and_the_digest() -> None:
    doc = folder_mosaic_json(IMAGE, method="best", compliance=FIT, tissue=TISSUE, scan_digest="ab" * 16)
    assert doc["px_per_mm"] == 8.0 and doc["origin_px"] == [20.0, 30.0] and (doc["width"], doc["height"]) == (80, 60)
    assert doc["method"] == "best" and doc["compliance_per_n"] == 0.006 and doc["gauge"] == 1.002
    assert doc["tissue"] == TISSUE and doc["scan_digest"] == "ab" * 16
    json.dumps(doc, allow_nan=False)
    bare = folder_mosaic_json(IMAGE, method="paper")
    assert not {"compliance_per_n", "gauge", "tissue", "scan_digest"} & set(bare)


def test_the_service_and_the_folder_agree_on_every_key_they_share() -> None:
    folder = folder_mosaic_json(IMAGE, method="best", compliance=FIT, tissue=TISSUE)
    served = mosaic_json(
        IMAGE,
        version=3,
        results_version=1,
        revisions=empty_revisions(),
        geometry=DziGeometry.for_mosaic(8.0),
        extent_mm=None,
        rows=[],
        status="done",
        method="best",
        compliance=FIT,
        tissue=TISSUE,
    )
    assert set(folder) <= set(served)
    assert {k: served[k] for k in folder} == folder
