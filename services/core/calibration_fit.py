"""Calibration fits (spec §2 "Calibration", paper §IV-B): Young's modulus E from the stretch of frames pressed
normally at known loads, and the Hooke constant kappa from IMU reference tilts against force differences.

Model (spec §2 rectification r = r' (1 - c F), c = nu / (E A)): a frame pressed normally at load F sees the
surface stretched about the principal point, r' = r / (1 - c F). Between a reference frame at load F0 and a
frame of the same place at load Fk the image scale is s_k = (1 - c F0) / (1 - c Fk), which is linear in c:
s_k - 1 = c (s_k Fk - F0).
Tilt (spec §2): F2 - F1 = 2 kappa S_Y sin(theta_x), F4 - F3 = 2 kappa S_X sin(theta_y).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.core.inputs.calibration import Calibration
from services.core.inputs.scan import Scan
from services.core.physics.force_model import interpolate_forces, load_state
from services.core.physics.tissue_model import HookeFit, fit_kappa_to_tilts
from services.core.registration.features import detect_features
from services.core.registration.vein_enhancement import enhance_veins

# Frame selection for the modulus fit (values from the task brief).
NORMAL_TILT_DEG = 0.05  # "pressed normally": |theta_x|, |theta_y| below this
MIN_EXTRA_LOAD_N = 1.0  # a calibration frame carries at least this much more than the reference
SAME_PLACE_MM = 3.0  # content shift at the principal point below this = the same place
MIN_MODULUS_FRAMES = 3
MAX_MODULUS_CANDIDATES = 150  # more normally-pressed frames than this are subsampled evenly (SIFT cost)
OUTLIER_MAD_FACTOR = 4.0  # one pass of rejecting scale outliers beyond 4 robust sigmas ...
OUTLIER_FLOOR = 2e-3  # ... but never tighter than a 0.2 % stretch

# Image measurement (values from the task brief).
SIFT_FEATURES = 1500
RATIO_TEST = 0.75
RANSAC_THRESHOLD_PX = 1.5
MIN_INLIERS = 20
MASK_ERODE_PX = 12  # keep keypoints whose descriptor window lies inside the field of view


@dataclass(frozen=True)
class ModulusFit:
    """Least-squares E (kPa) and c = nu / (E A) (1/N) from measured scales; residuals = model - measured."""

    young_modulus_kpa: float
    compliance_per_n: float
    n_frames: int
    residual_rms: float
    residuals: np.ndarray
    loads_n: np.ndarray
    scales: np.ndarray
    ref_load_n: float = float("nan")

    @property
    def predicted_scales(self) -> np.ndarray:
        """Return the model's scales (1 - c F0) / (1 - c Fk) for the fitted frames (dimensionless)."""
        c = self.compliance_per_n
        return (1.0 - c * self.ref_load_n) / (1.0 - c * self.loads_n)


@dataclass(frozen=True)
class ScaleMeasurements:
    """Similarity of frames relative to a reference frame: scale, content shift at the principal point (mm)
    and RANSAC inliers; NaN scale/shift where the estimate failed (< MIN_INLIERS inliers)."""

    indices: np.ndarray
    scales: np.ndarray
    shifts_mm: np.ndarray
    inliers: np.ndarray


@dataclass(frozen=True)
class CalibrationResult:
    """The fits, the calibration updated with whatever was fitted, and notes on what could not be fitted."""

    modulus: ModulusFit | None
    hooke: HookeFit | None
    calibration: Calibration
    notes: list[str] = field(default_factory=list)
    input_calibration: Calibration | None = None
    reference_seq: int | None = None
    modulus_seq: tuple[int, ...] = ()


# ----------------------------------------------------------------------------------------------- pure fits


def fit_young_modulus(
    ref_load_n: float, loads_n: np.ndarray, scales: np.ndarray, poisson_ratio: float, area_m2: float
) -> ModulusFit:
    """Return the ModulusFit: E in kPa from scales s_k of frames at loads F_k (N) relative to one at F0 (N).

    Linearised least squares (spec §2): s_k - 1 = c (s_k F_k - F0), c = sum(a b) / sum(a^2) with
    a = s_k F_k - F0, b = s_k - 1; E = nu / (c A) Pa. Non-finite pairs are ignored.
    """
    loads = np.asarray(loads_n, dtype=np.float64).ravel()
    s = np.asarray(scales, dtype=np.float64).ravel()
    if loads.shape != s.shape:
        raise ValueError(f"loads_n and scales differ in length ({len(loads)} vs {len(s)})")
    if not (math.isfinite(ref_load_n) and poisson_ratio > 0 and area_m2 > 0):
        raise ValueError("ref_load_n must be finite and poisson_ratio, area_m2 positive")
    ok = np.isfinite(loads) & np.isfinite(s)
    loads, s = loads[ok], s[ok]
    if len(s) == 0:
        raise ValueError("no frame with a measured scale to fit the modulus")
    a = s * loads - ref_load_n
    b = s - 1.0
    denom = float(np.sum(a * a))
    if denom <= 0.0:
        raise ValueError("the loads do not differ from the reference load: the modulus is not observable")
    c = float(np.sum(a * b)) / denom
    if not c > 0.0:
        raise ValueError(f"the measured stretch does not grow with load (fitted nu/(E A) = {c:.3g} /N)")
    predicted = (1.0 - c * ref_load_n) / (1.0 - c * loads)
    residuals = predicted - s
    return ModulusFit(
        young_modulus_kpa=poisson_ratio / (c * area_m2) / 1000.0,
        compliance_per_n=c,
        n_frames=len(s),
        residual_rms=float(np.sqrt(np.mean(residuals**2))),
        residuals=residuals,
        loads_n=loads,
        scales=s,
        ref_load_n=float(ref_load_n),
    )


def fit_hooke(
    imu_t_s: np.ndarray,
    imu_tilt_deg: np.ndarray,
    force_t_s: np.ndarray,
    forces_n: np.ndarray,
    sensor_separation_mm: tuple[float, float],
) -> HookeFit:
    """Return the HookeFit: kappa (N/mm) = sum(dF g) / sum(g^2) over both axes (spec §2 tilt equations).

    g_y = 2 S_Y sin(tilt_x) against dF_y = F2 - F1, g_x = 2 S_X sin(tilt_y) against dF_x = F4 - F3, forces
    interpolated at the IMU times; only IMU samples inside the force record and tilted >= MIN_TILT_DEG on
    an axis count for that axis.
    """
    t = np.asarray(imu_t_s, dtype=np.float64).ravel()
    tilt = np.asarray(imu_tilt_deg, dtype=np.float64).reshape(len(t), -1)
    if tilt.shape[1] != 2:
        raise ValueError(f"imu_tilt_deg: expected (K, 2) as (tilt_x, tilt_y) deg, got {tilt.shape}")
    ft = np.asarray(force_t_s, dtype=np.float64).ravel()
    if len(ft) == 0:
        raise ValueError("no force samples")
    inside = np.isfinite(t) & np.all(np.isfinite(tilt), axis=1) & (t >= ft.min()) & (t <= ft.max())
    t, tilt = t[inside], tilt[inside]
    if len(t) == 0:
        raise ValueError("no IMU sample falls inside the force record")
    return fit_kappa_to_tilts(tilt, interpolate_forces(ft, forces_n, t), sensor_separation_mm)


# ------------------------------------------------------------------------------------- image measurement


CENTRAL_RADIUS_MM = 25.0  # keypoints farther than this from the principal point are not used to fit E


def _prepare_frame(scan: Scan, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Return (undistorted 8-bit frame, 8-bit keypoint mask) for frame `index`."""
    calib = scan.calibration
    raw = np.asarray(scan.frame(index))
    if raw.ndim != 2:
        raise ValueError(f"frame {index}: expected a 2-D grayscale image, got shape {raw.shape}")
    if raw.dtype != np.uint8:
        raw = cv2.normalize(raw.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    valid = np.full(raw.shape, 255, np.uint8)
    if scan.mask is not None:
        if scan.mask.shape != raw.shape:
            raise ValueError(f"mask shape {scan.mask.shape} differs from the frame shape {raw.shape}")
        valid = np.where(scan.mask > 0, 255, 0).astype(np.uint8)
    if np.any(calib.D):
        img = cv2.undistort(raw, calib.K, calib.D)
        valid = cv2.undistort(valid, calib.K, calib.D)
        valid = np.where(valid > 127, 255, 0).astype(np.uint8)
    else:
        img = raw
    if scan.mask is not None or np.any(calib.D):
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * MASK_ERODE_PX + 1, 2 * MASK_ERODE_PX + 1))
        valid = cv2.erode(valid, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return img, valid


def _features(scan: Scan, index: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Return keypoints (pixels, float32) and descriptors of a frame's vein map, as registration detects them."""
    img, valid = _prepare_frame(scan, index)
    vein = enhance_veins(img, valid)
    found = detect_features(vein.image, vein.mask, "sift", target=SIFT_FEATURES)
    # only the central part of the window: far from the centre, deformation the spec §2 model does not
    # capture (tissue non-linearity) grows with the radius and would bias the fitted stretch
    centre = np.array(scan.calibration.principal_point)
    near = np.linalg.norm(found.points - centre, axis=1) <= CENTRAL_RADIUS_MM * scan.calibration.px_per_mm
    found = found.subset(near)
    desc = found.descriptors.astype(np.float32) if len(found) else None  # cv2.BFMatcher's L2 wants float32
    return found.points.astype(np.float32).reshape(-1, 2), desc


def measure_similarities(scan: Scan, ref_index: int, indices: list[int]) -> ScaleMeasurements:
    """Return each frame's similarity to the reference frame: scale, content shift at (cx, cy) in mm, inliers.

    Both frames undistorted, SIFT on the vein map (1500 adaptive features, inside the eroded mask), ratio 0.75, RANSAC
    partial-affine (1.5 px, seeded); scale = sqrt|det| of the 2x2 part, mapping reference -> frame pixels.
    """
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    ref_pts, ref_desc = _features(scan, ref_index)
    idx = np.asarray(list(indices), dtype=np.int64)
    scales = np.full(len(idx), np.nan)
    shifts = np.full((len(idx), 2), np.nan)
    inliers = np.zeros(len(idx), dtype=np.int64)
    cx, cy = scan.calibration.principal_point
    centre = np.array([cx, cy])
    for j, k in enumerate(idx):
        if ref_desc is None or len(ref_pts) < MIN_INLIERS:
            break
        pts, desc = _features(scan, int(k))
        if desc is None or len(pts) < MIN_INLIERS:
            continue
        pairs = matcher.knnMatch(ref_desc, desc, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO_TEST * p[1].distance]
        if len(good) < MIN_INLIERS:
            continue
        src = ref_pts[[m.queryIdx for m in good]]
        dst = pts[[m.trainIdx for m in good]]
        cv2.setRNGSeed(0)
        M, mask = cv2.estimateAffinePartial2D(
            src,
            dst,
            method=cv2.RANSAC,
            ransacReprojThreshold=RANSAC_THRESHOLD_PX,
            maxIters=5000,
            confidence=0.999,
        )
        n_in = int(mask.sum()) if mask is not None else 0
        inliers[j] = n_in
        if M is None or n_in < MIN_INLIERS:
            continue
        scales[j] = math.sqrt(abs(float(np.linalg.det(M[:, :2]))))
        shifts[j] = (M[:, :2] @ centre + M[:, 2] - centre) / scan.calibration.px_per_mm
    return ScaleMeasurements(indices=idx, scales=scales, shifts_mm=shifts, inliers=inliers)


def measure_scales(scan: Scan, ref_index: int, indices: list[int]) -> np.ndarray:
    """Return the scale (dimensionless) of each frame relative to the reference frame; NaN where it failed."""
    return measure_similarities(scan, ref_index, indices).scales


# ------------------------------------------------------------------------------------------ whole scan


def _fit_modulus_from_frames(
    scan: Scan, calib: Calibration, notes: list[str]
) -> tuple[ModulusFit | None, int | None, tuple[int, ...]]:
    """Return (fit or None, reference seq, seqs used) choosing frames as the module docstring says."""
    n = len(scan)
    if n < 1 + MIN_MODULUS_FRAMES:
        notes.append(f"E not fitted: the scan has {n} frames; need a reference and {MIN_MODULUS_FRAMES} more")
        return None, None, ()
    forces = interpolate_forces(scan.force_t_s, scan.forces_n, scan.frame_t_s)
    states = [load_state(f, calib) for f in forces]
    fz = np.array([s.fz_n for s in states])
    tilt = np.degrees(np.array([[s.theta_x_rad, s.theta_y_rad] for s in states]))
    normal = np.all(np.abs(tilt) < NORMAL_TILT_DEG, axis=1)
    if not normal.any():
        notes.append(f"E not fitted: no frame is pressed normally (|tilt| < {NORMAL_TILT_DEG} deg)")
        return None, None, ()
    ref = int(np.flatnonzero(normal)[np.argmin(fz[normal])])
    ref_seq = int(scan.frame_seq[ref])
    if ref != int(np.argmin(fz)):
        notes.append("the least-loaded frame is tilted; the reference is the least-loaded untilted frame")
    cand = np.flatnonzero(normal & (fz >= fz[ref] + MIN_EXTRA_LOAD_N))
    if len(cand) < MIN_MODULUS_FRAMES:
        notes.append(
            f"E not fitted: {len(cand)} frames pressed normally with >= {MIN_EXTRA_LOAD_N} N more than the "
            f"reference ({fz[ref]:.2f} N); need {MIN_MODULUS_FRAMES}"
        )
        return None, ref_seq, ()
    if len(cand) > MAX_MODULUS_CANDIDATES:
        notes.append(f"{len(cand)} candidate frames for E; {MAX_MODULUS_CANDIDATES} used, evenly spaced")
        cand = cand[np.linspace(0, len(cand) - 1, MAX_MODULUS_CANDIDATES).round().astype(int)]
    meas = measure_similarities(scan, ref, [int(i) for i in cand])
    measured = np.isfinite(meas.scales)
    same = measured & (np.linalg.norm(np.nan_to_num(meas.shifts_mm, nan=np.inf), axis=1) < SAME_PLACE_MM)
    if int(same.sum()) < MIN_MODULUS_FRAMES:
        notes.append(
            f"E not fitted: of {len(cand)} normally pressed frames, {int((~measured).sum())} could not be "
            f"matched to the reference and {int((measured & ~same).sum())} are not at the same place "
            f"(shift >= {SAME_PLACE_MM} mm); need {MIN_MODULUS_FRAMES}"
        )
        return None, ref_seq, ()
    use = cand[same]
    scales = meas.scales[same]
    nu, area = calib.poisson_ratio, calib.scanner_area_m2
    try:
        fit = fit_young_modulus(float(fz[ref]), fz[use], scales, nu, area)
        res = fit.residuals
        mad = float(np.median(np.abs(res - np.median(res)))) * 1.4826
        keep = np.abs(res) <= max(OUTLIER_MAD_FACTOR * mad, OUTLIER_FLOOR)
        if not keep.all() and int(keep.sum()) >= MIN_MODULUS_FRAMES:
            notes.append(f"E: {int((~keep).sum())} frame(s) with an outlying scale left out of the fit")
            use, scales = use[keep], scales[keep]
            fit = fit_young_modulus(float(fz[ref]), fz[use], scales, nu, area)
    except ValueError as exc:
        notes.append(f"E not fitted: {exc}")
        return None, ref_seq, ()
    return fit, ref_seq, tuple(int(scan.frame_seq[i]) for i in use)


def calibrate_scan(scan: Scan) -> CalibrationResult:
    """Return the CalibrationResult of fitting kappa (from imu.csv) and then E (from frames) on one scan."""
    calib = scan.calibration
    notes: list[str] = []
    hooke: HookeFit | None = None
    if scan.imu_t_s is None or scan.imu_tilt_deg is None:
        notes.append("kappa not fitted: the scan has no IMU reference angles (imu.csv)")
    else:
        try:
            hooke = fit_hooke(
                scan.imu_t_s, scan.imu_tilt_deg, scan.force_t_s, scan.forces_n, calib.sensor_separation_mm
            )
        except ValueError as exc:
            notes.append(f"kappa not fitted: {exc}")
    # The tilt test that selects the E frames uses the fitted kappa when there is one.
    working = calib.with_overrides(hooke_n_per_mm=hooke.hooke_n_per_mm) if hooke else calib
    modulus, ref_seq, used = _fit_modulus_from_frames(scan, working, notes)
    updates: dict[str, float] = {}
    if hooke is not None:
        updates["hooke_n_per_mm"] = hooke.hooke_n_per_mm
    if modulus is not None:
        updates["young_modulus_kpa"] = modulus.young_modulus_kpa
    return CalibrationResult(
        modulus=modulus,
        hooke=hooke,
        calibration=calib.with_overrides(**updates) if updates else calib,
        notes=notes,
        input_calibration=calib,
        reference_seq=ref_seq,
        modulus_seq=used,
    )


def format_calibration_report(result: CalibrationResult) -> str:
    """Return a human-readable text table of the fits, their residuals and the notes."""
    lines = ["Calibration fit (spec §2, paper §IV-B)", ""]
    before = result.input_calibration
    m = result.modulus
    if m is None:
        lines.append("Young's modulus E: not fitted")
    else:
        lines.append(
            f"Young's modulus E: {m.young_modulus_kpa:.3f} kPa  (nu/(E A) = {m.compliance_per_n:.6f} /N, "
            f"nu = {result.calibration.poisson_ratio:g}, A = {result.calibration.scanner_area_m2:g} m^2)"
        )
        ref = "?" if result.reference_seq is None else str(result.reference_seq)
        lines.append(f"  reference frame seq {ref} at {m.ref_load_n:.3f} N; {m.n_frames} frames pressed normally")
        lines.append(f"  {'seq':>7} {'load N':>9} {'scale meas':>11} {'scale model':>12} {'residual':>10}")
        seqs = list(result.modulus_seq) if len(result.modulus_seq) == m.n_frames else ["-"] * m.n_frames
        for sq, f, s, p, r in zip(seqs, m.loads_n, m.scales, m.predicted_scales, m.residuals, strict=True):
            lines.append(f"  {sq!s:>7} {f:9.3f} {s:11.6f} {p:12.6f} {r:+10.6f}")
        lines.append(f"  residual RMS: {m.residual_rms:.6f} (stretch, dimensionless)")
    lines.append("")
    h = result.hooke
    if h is None:
        lines.append("Hooke constant kappa: not fitted")
    else:
        lines.append(
            f"Hooke constant kappa: {h.hooke_n_per_mm:.4f} N/mm from {h.n_samples} IMU axis-samples, "
            f"residual RMS {h.residual_rms_n:.4f} N"
        )
    if before is not None:
        lines.append("")
        lines.append("Calibration values (before -> after):")
        lines.append(f"  young_modulus_kpa: {before.young_modulus_kpa:g} -> {result.calibration.young_modulus_kpa:g}")
        lines.append(f"  hooke_n_per_mm:    {before.hooke_n_per_mm:g} -> {result.calibration.hooke_n_per_mm:g}")
    if result.notes:
        lines.append("")
        lines.append("Notes:")
        lines.extend(f"  - {note}" for note in result.notes)
    return "\n".join(lines) + "\n"
