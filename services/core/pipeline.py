"""The reconstruction pipeline: a scan in, the probe path, the mosaic and the force layer out (spec §1-§4)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.core.inputs.calibration import Calibration
from services.core.inputs.scan import Scan
from services.core.lookahead import in_order_ahead
from services.core.methods import MethodOptions
from services.core.mosaic.canvas import MosaicImage
from services.core.path_rows import UNCOUNTED, PathRow, PlacedCounts
from services.core.physics.compliance import ComplianceFit
from services.core.physics.force_model import interpolate_forces
from services.core.physics.tissue_model import reference_tilts_at
from services.core.registration.frame_prep import (
    PreparedFrame,
    estimate_flat_field,
    estimate_window_mask,
    prepare_frame,
)
from services.core.registration.outcome import STATUS_OK
from services.core.session_reconstruction import SessionReconstruction
from services.core.similarity import Similarity

__all__ = ["Reconstruction", "reconstruct"]

Progress = Callable[[int, int], None]
MASK_SAMPLE_FRAMES = 24  # the window mask and vignetting come from the first frames, as a live session must


@dataclass(frozen=True)
class Reconstruction:
    """The outputs of a reconstruction: path rows, placed poses, mosaic, compliance fit and timing."""

    method: str
    rows: list[PathRow]
    poses: dict[int, Similarity]
    mosaic: MosaicImage
    compliance: ComplianceFit | None
    seconds: float
    learned: dict[str, Any] = field(default_factory=dict)  # SessionReconstruction.learned_model()
    keyframes: int = 0  # placed frames registered by their features (the rest tracked: MethodOptions.track_overlap)
    # the final graph's edges: frame i, frame j, measured relative yaw (deg), loop 0/1, the yaw's SD in the graph (deg),
    # the mean load of its frames (N) (SessionReconstruction.edge_yaws)
    edge_yaws: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    placed: PlacedCounts = UNCOUNTED  # placed frames tracked and stitched (SessionReconstruction.placed_counts)

    @property
    def closures(self) -> int:
        """Return the loop-closure edges in the final pose graph (spanning more than MethodOptions.loop_gap frames)."""
        return int(np.count_nonzero(self.edge_yaws[:, 3]))

    @property
    def estimate_mm(self) -> np.ndarray:
        """Return the (N, 2) frame-centre positions in mm, NaN where not registered."""
        return np.array([[r.x_mm, r.y_mm] for r in self.rows], float)

    @property
    def registered(self) -> np.ndarray:
        """Return the (N,) mask of frames with status ok."""
        return np.array([r.status == STATUS_OK for r in self.rows])


def frame_forces(scan: Scan) -> np.ndarray:
    """Return the sensor forces (N, 4) in N interpolated at each frame's timestamp (spec §2)."""
    return interpolate_forces(scan.force_t_s, scan.forces_n, scan.frame_t_s)


def frame_imu(scan: Scan) -> np.ndarray:
    """Return the IMU's (tilt_x, tilt_y) deg (N, 2) at each frame's timestamp, NaN where it has no sample around."""
    return reference_tilts_at(scan.frame_t_s, scan.imu_t_s, scan.imu_tilt_deg)


def window_setup_of(
    frames: Sequence[np.ndarray], mask: np.ndarray | None, options: MethodOptions
) -> tuple[np.ndarray, np.ndarray | None]:
    """Return (window mask uint8 0/255, vignetting gain or None) from the first frames (MASK_SAMPLE_FRAMES).

    The one window set-up, offline and live: the mask is the scan's own (mask.png) when it has one, else
    found from the frames; the gain is skipped when the method does not flat-field.
    """
    frames = list(frames)[:MASK_SAMPLE_FRAMES]
    mask = mask if mask is not None else estimate_window_mask(frames)
    flat = estimate_flat_field(frames, mask) if options.flat_field else None
    return mask, flat


def window_setup(scan: Scan, options: MethodOptions) -> tuple[np.ndarray, np.ndarray | None]:
    """Return (window mask, vignetting gain or None) of a scan from its first frames, read once (window_setup_of)."""
    frames = [scan.frame(i) for i in range(min(len(scan), MASK_SAMPLE_FRAMES))]
    return window_setup_of(frames, scan.mask, options)


def window_radius_mm(mask: np.ndarray, calib: Calibration) -> float:
    """Return the radius (mm) of the circle with the window's area."""
    return math.sqrt(float(np.count_nonzero(mask)) / math.pi) / calib.px_per_mm


def prepare_scan_frame(
    scan: Scan,
    index: int,
    forces_n: np.ndarray,
    mask: np.ndarray,
    flat: np.ndarray | None,
    options: MethodOptions,
    imu_tilt_deg: np.ndarray | None = None,
) -> PreparedFrame:
    """Return frame `index` of a scan prepared for registration (see frame_prep.prepare_frame)."""
    return prepare_frame(
        scan.frame(index),
        index=int(scan.frame_seq[index]),  # registration indexes frames by seq, as a live session does
        seq=int(scan.frame_seq[index]),
        t_s=float(scan.frame_t_s[index]),
        forces_n=forces_n,
        calib=scan.calibration,
        mask=mask,
        flat=flat,
        options=options,
        imu_tilt_deg=imu_tilt_deg,
    )


def prepared_frames(
    scan: Scan, forces: np.ndarray, mask: np.ndarray, flat: np.ndarray | None, options: MethodOptions
) -> Iterator[PreparedFrame]:
    """Yield prepared frames in order, preparing up to a few ahead on a thread pool (OpenCV frees the GIL)."""
    imu = frame_imu(scan)

    def job(i: int) -> PreparedFrame:
        return prepare_scan_frame(scan, i, forces[i], mask, flat, options, imu[i])

    yield from in_order_ahead(job, range(len(scan)), ahead=4)


def reconstruct(scan: Scan, options: MethodOptions, progress: Progress | None = None) -> Reconstruction:
    """Return the path, mosaic and force layer of a scan by the given method (the pipeline's steps in order)."""
    started = time.perf_counter()
    calib = scan.calibration
    forces = frame_forces(scan)  # 1. forces at frame times
    mask, flat = window_setup(scan, options)  # 2-3. the window's field of view; the IR ring's vignetting
    session = SessionReconstruction(calib, options, window_radius_mm(mask, calib))
    for done, pf in enumerate(prepared_frames(scan, forces, mask, flat, options), 1):  # 4. rectify + features
        session.add_next(pf)  # 5. contact, then register against what is placed (+ refinement on loop closures)
        if progress:
            progress(done, len(scan))
    session.finish()  # 6-7. final global refinement; compliance self-calibration (path in true mm)
    mosaic = session.render()  # 8. stitch the vein and force layers
    return Reconstruction(
        options.name,
        session.path_rows(),
        session.final_poses(),
        mosaic,
        session.compliance,
        time.perf_counter() - started,
        session.learned_model(),
        len(session.registrar.features),
        session.edge_yaws(),
        placed=session.placed_counts(),
    )
