"""The reconstruction pipeline: a scan in, the probe path, the mosaic and the force layer out (spec §1-§4)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from services.calibration import Calibration
from services.compliance import ComplianceFit, fit_compliance
from services.force_model import interpolate_forces
from services.frame_prep import (
    PreparedFrame,
    estimate_flat_field,
    estimate_window_mask,
    load_map_n,
    prepare_frame,
)
from services.methods import MethodOptions
from services.mosaic import FrameLayers, MosaicImage, SparseCanvas, blend_weight
from services.registrar import STATUS_OK, FrameResult, Registrar
from services.registration import Similarity
from services.scan import Scan

Progress = Callable[[int, int], None]
MASK_SAMPLE_FRAMES = 24
PATH_COLUMNS = (
    "seq",
    "t_s",
    "x_mm",
    "y_mm",
    "yaw_deg",
    "fz_n",
    "tilt_x_deg",
    "tilt_y_deg",
    "stretch",
    "inliers",
    "status",
)


@dataclass(frozen=True)
class PathRow:
    """One row of the path (spec §4); x, y, yaw are NaN for frames that were not registered."""

    seq: int
    t_s: float
    x_mm: float
    y_mm: float
    yaw_deg: float
    fz_n: float
    tilt_x_deg: float
    tilt_y_deg: float
    stretch: float
    inliers: int
    status: str


@dataclass(frozen=True)
class StitchFrame:
    """What the stitcher keeps of a frame: rectified image, window mask and load map inputs."""

    prepared: PreparedFrame
    blurred: bool


@dataclass(frozen=True)
class Reconstruction:
    """The outputs of a reconstruction: path rows, placed poses, mosaic, compliance fit and timing."""

    method: str
    rows: list[PathRow]
    poses: dict[int, Similarity]
    mosaic: MosaicImage
    compliance: ComplianceFit | None
    seconds: float

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


def window_mask(scan: Scan) -> np.ndarray:
    """Return the window mask: mask.png when the scan has one, else found from a sample of frames."""
    if scan.mask is not None:
        return scan.mask
    picks = np.linspace(0, len(scan) - 1, min(len(scan), MASK_SAMPLE_FRAMES)).astype(int)
    return estimate_window_mask([scan.frame(int(i)) for i in picks])


def flat_field(scan: Scan, mask: np.ndarray, options: MethodOptions) -> np.ndarray | None:
    """Return the vignetting gain estimated from a sample of frames, or None when the method skips it."""
    if not options.flat_field:
        return None
    picks = np.linspace(0, len(scan) - 1, min(len(scan), MASK_SAMPLE_FRAMES)).astype(int)
    return estimate_flat_field([scan.frame(int(i)) for i in picks], mask)


def window_radius_mm(mask: np.ndarray, calib: Calibration) -> float:
    """Return the radius (mm) of the circle with the window's area."""
    return math.sqrt(float(np.count_nonzero(mask)) / math.pi) / calib.px_per_mm


def prepared_frames(
    scan: Scan, forces: np.ndarray, mask: np.ndarray, flat: np.ndarray | None, options: MethodOptions
) -> Iterator[PreparedFrame]:
    """Yield prepared frames in order, preparing up to a few ahead on a thread pool (OpenCV frees the GIL)."""

    def job(i: int) -> PreparedFrame:
        return prepare_frame(
            scan.frame(i),
            index=i,
            seq=int(scan.frame_seq[i]),
            t_s=float(scan.frame_t_s[i]),
            forces_n=forces[i],
            calib=scan.calibration,
            mask=mask,
            flat=flat,
            options=options,
        )

    with ThreadPoolExecutor(max_workers=2) as pool:
        ahead = 4
        futures = [pool.submit(job, i) for i in range(min(ahead, len(scan)))]
        for i in range(len(scan)):
            nxt = i + ahead
            if nxt < len(scan):
                futures.append(pool.submit(job, nxt))
            yield futures[i].result()
            futures[i] = None  # type: ignore[call-overload]


def self_calibrate(
    registrar: Registrar, results: list[FrameResult], prepared_loads: dict[int, float], calib: Calibration
) -> ComplianceFit | None:
    """Return the compliance fit from the placed frames' similarity scales and loads (see compliance.py)."""
    placed = [r.index for r in results if r.status == STATUS_OK]
    scales = np.array([abs(registrar.poses[i].a) for i in placed])
    loads = np.array([prepared_loads[i] for i in placed])
    return fit_compliance(scales, loads, calib.compliance_per_n)


def stitch(
    kept: dict[int, StitchFrame], poses: dict[int, Similarity], calib: Calibration, rigid: bool
) -> MosaicImage:
    """Return the mosaic of the placed, sharp frames at their final poses (vein, force and coverage)."""
    canvas = SparseCanvas(calib.px_per_mm)
    weights: dict[bytes, np.ndarray] = {}
    for i, frame in sorted(kept.items()):
        if i not in poses or frame.blurred:
            continue
        pf = frame.prepared
        key = pf.mask.tobytes()[:: max(1, pf.mask.size // 4096)]
        weight = weights.setdefault(key, blend_weight(pf.mask))
        layers = FrameLayers(
            intensity=pf.image.astype(np.float32) / 255.0,
            weight=weight,
            force_n=load_map_n(calib, pf.load),
            centre_px=calib.principal_point,
            px_per_mm=calib.px_per_mm,
        )
        canvas.paste(layers, poses[i].rigid() if rigid else poses[i])
    return canvas.render()


def path_rows(
    scan: Scan, results: list[FrameResult], poses: dict[int, Similarity], prepared: dict[int, PreparedFrame]
) -> list[PathRow]:
    """Return one PathRow per frame (spec §4) from the final poses and statuses."""
    rows = []
    for r in results:
        pf = prepared[r.index]
        pose = poses.get(r.index) if r.status == STATUS_OK else None
        x, y, yaw = (pose.t.real, pose.t.imag, math.degrees(pose.yaw_rad)) if pose else (math.nan,) * 3
        rows.append(
            PathRow(
                seq=int(scan.frame_seq[r.index]),
                t_s=float(scan.frame_t_s[r.index]),
                x_mm=x,
                y_mm=y,
                yaw_deg=yaw,
                fz_n=pf.load.fz_n,
                tilt_x_deg=math.degrees(pf.load.theta_x_rad),
                tilt_y_deg=math.degrees(pf.load.theta_y_rad),
                stretch=pf.stretch,
                inliers=r.inliers,
                status=r.status,
            )
        )
    return rows


def reconstruct(scan: Scan, options: MethodOptions, progress: Progress | None = None) -> Reconstruction:
    """Return the path, mosaic and force layer of a scan by the given method (the pipeline's steps in order)."""
    started = time.perf_counter()
    calib = scan.calibration
    forces = frame_forces(scan)  # 1. forces at frame times
    mask = window_mask(scan)  # 2. the window's field of view
    flat = flat_field(scan, mask, options)  # 3. the IR ring's vignetting
    registrar = Registrar(options, calib.px_per_mm, window_radius_mm(mask, calib))
    results: list[FrameResult] = []
    kept: dict[int, StitchFrame] = {}
    for pf in prepared_frames(scan, forces, mask, flat, options):  # 4. rectify + features (parallel)
        result = registrar.add(pf)  # 5. register against what is placed
        results.append(result)
        kept[pf.index] = StitchFrame(pf, result.blurred)
        if progress:
            progress(pf.index + 1, len(scan))
    if options.refine:
        registrar.refine()  # 6. global pose-graph refinement
    prepared = {i: k.prepared for i, k in kept.items()}
    compliance = None
    poses = dict(registrar.poses)
    if options.self_calibrate:  # 7. compliance self-calibration: path in true mm
        compliance = self_calibrate(registrar, results, {i: p.load.fz_n for i, p in prepared.items()}, calib)
        if compliance is not None:
            g = compliance.gauge
            poses = {i: Similarity(p.a / g, p.t / g) for i, p in poses.items()}
    mosaic = stitch(kept, poses, calib, options.rigid_stitch)  # 8. stitch vein and force layers
    rows = path_rows(scan, results, poses, prepared)
    return Reconstruction(options.name, rows, poses, mosaic, compliance, time.perf_counter() - started)
