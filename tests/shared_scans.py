"""Where the shared reference scans are: ../shared/scans next to this checkout (absent on a bare clone)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from services.core.inputs.scan import Scan
from services.store.scan_folder import read_scan_folder

SHARED_SCANS = Path(__file__).resolve().parents[2] / "shared" / "scans"

SHARED_CLINICAL = SHARED_SCANS / "clinical_veins_24"


def clinical_until(last_seq: int, mask: bool = True) -> Scan:
    """Return clinical_veins_24 (lifts, frames in the air, dropped frames) up to seq `last_seq`.

    mask=False leaves mask.png out, as a live session has none (the window is estimated from the frames).
    """
    scan = read_scan_folder(SHARED_CLINICAL)
    n = int(np.searchsorted(scan.frame_seq, last_seq, side="right"))
    load = scan.frame_loader
    return dataclasses.replace(
        scan,
        frame_seq=scan.frame_seq[:n],
        frame_t_s=scan.frame_t_s[:n],
        frame_loader=load,
        mask=scan.mask if mask else None,
        reference_mm=None if scan.reference_mm is None else scan.reference_mm[:n],
        reference_angles_deg=None if scan.reference_angles_deg is None else scan.reference_angles_deg[:n],
    )
