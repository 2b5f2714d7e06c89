"""Probe-path accuracy against a reference track (spec §4): RMSE, max error, final drift, error ratio, and where
the error lies (the path's scale and turn about frame 0, and the RMSE left after them)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

MIN_COMPARED = 2  # frame 0 is the origin of both paths: one compared frame measures nothing


@dataclass(frozen=True)
class AccuracyReport:
    """Accuracy of an estimated path against a reference, both in frame 0's coordinates (mm, spec §4).

    errors_mm (N,) holds the per-frame Euclidean error in mm, NaN where the frame is not registered or has
    no reference. error_ratio_pct = 100 * final_drift_mm / path_length_mm (NaN for a zero-length path).
    With fewer than MIN_COMPARED frames compared (e.g. only frame 0, the origin by definition) the figures
    are NaN: an error of 0 there says nothing about the method, so it must not read as a perfect score.
    global_error: where the error lies (GlobalError: the path's scale and turn about frame 0, and what is left
    after them), None with too few frames compared.
    registered_fraction: the share of the frames with a reference (spec §4: every frame that touched the skin)
    that is registered; n_registered_without_reference: registered frames the reference has no row for (on a
    clinical scan, frames taken in the air: none should be).
    """

    rmse_mm: float
    max_error_mm: float
    final_drift_mm: float
    path_length_mm: float
    error_ratio_pct: float
    registered_fraction: float
    n_frames: int
    n_registered: int
    n_with_reference: int
    errors_mm: np.ndarray
    global_error: GlobalError | None = None
    n_registered_without_reference: int = 0

    @property
    def n_compared(self) -> int:
        """Return the number of frames both registered and with a reference."""
        return int(np.count_nonzero(np.isfinite(self.errors_mm)))

    @property
    def meaningful(self) -> bool:
        """Return True when enough frames were compared for the figures to say anything."""
        return self.n_compared >= MIN_COMPARED

    def summary(self) -> str:
        """Return a one-line human summary that always states how much of the scan the figures cover."""
        reg = f"{self.n_registered}/{self.n_frames} frames registered ({100 * self.registered_fraction:.1f} %)"
        if self.n_with_reference < self.n_frames:  # a clinical scan: the reference has the frames on the skin
            on = self.n_registered - self.n_registered_without_reference
            reg = (
                f"{on}/{self.n_with_reference} frames with a reference registered ({100 * self.registered_fraction:.1f}"
                f" %), {self.n_registered_without_reference} of the {self.n_frames - self.n_with_reference} without one"
            )
        if not self.meaningful:
            return f"accuracy not measurable: {reg}, {self.n_compared} compared with the reference"
        text = f"RMSE {self.rmse_mm:.3f} mm, max {self.max_error_mm:.3f} mm, final drift {self.final_drift_mm:.3f} mm"
        if math.isfinite(self.error_ratio_pct):
            text += f", error ratio {self.error_ratio_pct:.3f}% over {self.path_length_mm:.0f} mm"
        text += f" — over the {self.n_compared} registered frames with a reference; {reg}"
        if self.n_registered - self.n_registered_without_reference < self.n_with_reference:
            text += "; frames not registered are not in these figures"
        return text

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-able dict: the figures (NaN as None) and errors_mm as a list with None for NaN."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "rmse_mm": num(self.rmse_mm),
            "max_error_mm": num(self.max_error_mm),
            "final_drift_mm": num(self.final_drift_mm),
            "path_length_mm": num(self.path_length_mm),
            "error_ratio_pct": num(self.error_ratio_pct),
            "registered_fraction": num(self.registered_fraction),
            "n_frames": int(self.n_frames),
            "n_registered": int(self.n_registered),
            "n_with_reference": int(self.n_with_reference),
            "n_registered_without_reference": int(self.n_registered_without_reference),
            "n_compared": self.n_compared,
            "meaningful": self.meaningful,
            "errors_mm": [num(float(e)) for e in self.errors_mm],
            "global_error": None if self.global_error is None else self.global_error.to_dict(),
        }


LEAD_STEP_MM = (0.05, 10.0)  # a compared row moves (GlobalError.lead_mm) when both its steps are within these


@dataclass(frozen=True)
class GlobalError:
    """How much of a path's error is one global map about frame 0 (issue 14's decomposition).

    The estimate is fitted as estimate ~ b * reference about frame 0 (b complex: a similarity without
    translation, least squares over the compared frames). scale_pct = 100 (|b| - 1): + when the estimated path
    is larger than the reference; turn_deg: arg(b), the estimate turned from the reference in the sense of
    spec §4's yaw (x toward y). after_similarity_mm: the RMSE (mm) left once the estimate is mapped back by 1/b,
    in the reference's millimetres; after_linear_mm: that left after the best 2x2 linear map of the estimate onto
    the reference (reference ~ M estimate: scale, turn, stretch and shear; NaN for a straight path, which does not
    determine one). A small after_similarity_mm against the RMSE means the path's shape is right and its level or
    turn is not. lead_mm: the mean, over the frames that move, of what the similarity leaves along each one's
    direction of travel (the reference's, between its neighbours; + = the path runs ahead of the reference): a
    skin drag that is not undone in full leaves the path ahead by what remains of it, whichever way each stroke
    goes (NaN when no frame moves).
    """

    scale_pct: float
    turn_deg: float
    after_similarity_mm: float
    after_linear_mm: float
    lead_mm: float = math.nan

    def summary(self) -> str:
        """Return a one-line human summary: the path's scale and turn about frame 0 and the RMSE left after them."""
        lead = f", its mean along the travel {self.lead_mm:+.3f} mm (+ = ahead)" if math.isfinite(self.lead_mm) else ""
        return (
            f"where the error lies: the path {self.scale_pct:+.2f} % in scale (+ = too large) and turned"
            f" {self.turn_deg:+.3f} deg about frame 0; {self.after_similarity_mm:.3f} mm left after that (its shape)"
            f"{lead}"
        )

    def to_dict(self) -> dict[str, float | None]:
        """Return the five figures as a JSON-able dict (%, deg, mm, mm, mm; None where not defined)."""
        fields = ("scale_pct", "turn_deg", "after_similarity_mm", "after_linear_mm", "lead_mm")
        return {name: (v if math.isfinite(v := float(getattr(self, name))) else None) for name in fields}


def global_error(estimate_mm: np.ndarray, reference_mm: np.ndarray) -> GlobalError | None:
    """Return the GlobalError (%, deg, mm) of compared rows (finite (N, 2) pairs), None if they span no extent."""
    est = np.asarray(estimate_mm, np.float64).reshape(-1, 2)
    ref = np.asarray(reference_mm, np.float64).reshape(-1, 2)
    e = est[:, 0] + 1j * est[:, 1]
    r = ref[:, 0] + 1j * ref[:, 1]
    spread = float(np.vdot(r, r).real)
    if len(r) < MIN_COMPARED or spread <= 1e-12:
        return None
    b = complex(np.vdot(r, e) / spread)  # least squares of e ~ b r
    if abs(b) < 1e-12:
        return None
    left = e / b - r
    after_similarity = float(np.sqrt(np.mean(np.abs(left) ** 2)))
    linear, _, rank, _ = np.linalg.lstsq(est, ref, rcond=None)  # ref ~ est @ linear
    after_linear = float(np.sqrt(np.mean(np.sum((ref - est @ linear) ** 2, axis=1)))) if rank == 2 else math.nan
    turn = math.degrees(math.atan2(b.imag, b.real))
    return GlobalError(100.0 * (abs(b) - 1.0), turn, after_similarity, after_linear, _lead_mm(left, r))


def _lead_mm(left: np.ndarray, reference: np.ndarray) -> float:
    """Return the mean of complex errors `left` (mm) along the reference's direction of travel at each row, taken
    between its neighbours where both steps are LEAD_STEP_MM long (a lift's jump or a still probe has none)."""
    if len(reference) < 3:
        return math.nan
    before, after = reference[1:-1] - reference[:-2], reference[2:] - reference[1:-1]
    moving = np.all([(LEAD_STEP_MM[0] < np.abs(d)) & (np.abs(d) < LEAD_STEP_MM[1]) for d in (before, after)], axis=0)
    if not np.any(moving):
        return math.nan
    step = (before + after)[moving]
    return float(np.mean((left[1:-1][moving] * np.conj(step / np.abs(step))).real))


def _as_path(name: str, value: np.ndarray) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array of x, y in mm, got shape {arr.shape}")
    return arr


def reference_path_length_mm(reference_mm: np.ndarray) -> float:
    """Return the length (mm) of the reference track: the sum of steps between consecutive known rows."""
    ref = _as_path("reference_mm", reference_mm)
    known = ref[np.all(np.isfinite(ref), axis=1)]
    if len(known) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(known, axis=0), axis=1)))


def evaluate_path(estimate_mm: np.ndarray, registered: np.ndarray, reference_mm: np.ndarray) -> AccuracyReport:
    """Return the AccuracyReport (mm, %) of an estimated path against a reference, no alignment (spec §4).

    estimate_mm (N, 2) with NaN rows for frames not placed; registered (N,) bool; reference_mm (N, 2) with
    NaN rows where unknown. A frame is compared when it is registered, placed and has a reference.
    """
    est = _as_path("estimate_mm", estimate_mm)
    ref = _as_path("reference_mm", reference_mm)
    reg = np.asarray(registered)
    if reg.ndim != 1:
        raise ValueError(f"registered: expected an (N,) boolean array, got shape {reg.shape}")
    reg = reg.astype(bool)
    n = len(est)
    if len(ref) != n or len(reg) != n:
        raise ValueError(f"length mismatch: estimate has {n} frames, registered {len(reg)}, reference {len(ref)}")
    if n == 0:
        raise ValueError("no frames to evaluate")
    has_ref = np.all(np.isfinite(ref), axis=1)
    placed = reg & np.all(np.isfinite(est), axis=1)
    compared = placed & has_ref
    if not np.any(compared):
        raise ValueError(
            "nothing to compare: no frame is both registered and has a reference position "
            f"({int(reg.sum())} registered, {int(has_ref.sum())} with a reference, of {n})"
        )
    errors = np.full(n, np.nan)
    errors[compared] = np.linalg.norm(est[compared] - ref[compared], axis=1)
    valid = errors[compared]
    length = reference_path_length_mm(ref)
    if len(valid) >= MIN_COMPARED:
        rmse, max_error = float(np.sqrt(np.mean(valid**2))), float(np.max(valid))
        final_drift = float(errors[np.flatnonzero(compared)[-1]])
        ratio = 100.0 * final_drift / length if length > 0 else float("nan")
    else:
        rmse = max_error = final_drift = ratio = float("nan")
    return AccuracyReport(
        rmse_mm=rmse,
        max_error_mm=max_error,
        final_drift_mm=final_drift,
        path_length_mm=length,
        error_ratio_pct=ratio,
        registered_fraction=float(np.count_nonzero(reg & has_ref)) / max(int(has_ref.sum()), 1),
        n_frames=n,
        n_registered=int(reg.sum()),
        n_with_reference=int(has_ref.sum()),
        errors_mm=errors,
        global_error=global_error(est[compared], ref[compared]),
        n_registered_without_reference=int(np.count_nonzero(reg & ~has_ref)),
    )


def evaluate_angles(estimate_deg: np.ndarray, registered: np.ndarray, reference_deg: np.ndarray) -> dict[str, Any]:
    """Return the RMS and max errors (deg) of yaw and tilts against a tracker's (spec §4), per angle known.

    estimate_deg, reference_deg: (N, 3) yaw, tilt_x, tilt_y in degrees, NaN where unknown. Yaw is compared on
    registered frames only (it is a pose); the tilts on every frame with both values (they come from the loads).
    Angles with fewer than MIN_COMPARED frames compared are left out. Yaw differences are wrapped to +-180.
    """
    est = np.asarray(estimate_deg, np.float64).reshape(-1, 3)
    ref = np.asarray(reference_deg, np.float64).reshape(-1, 3)
    reg = np.asarray(registered, bool).ravel()
    out: dict[str, Any] = {}
    for k, name in enumerate(("yaw", "tilt_x", "tilt_y")):
        diff = est[:, k] - ref[:, k]
        if name == "yaw":
            diff = (diff + 180.0) % 360.0 - 180.0
            diff = np.where(reg, diff, np.nan)
        valid = diff[np.isfinite(diff)]
        if len(valid) < MIN_COMPARED:
            continue
        out[f"{name}_rmse_deg"] = float(np.sqrt(np.mean(valid**2)))
        out[f"{name}_max_error_deg"] = float(np.max(np.abs(valid)))
        out[f"{name}_compared"] = len(valid)
    return out


HIGH_LOAD_QUANTILE = 2.0 / 3.0  # edge_yaw_bias's high-load loop closures: their mean load in the top third


def edge_yaw_bias(edge_yaws: np.ndarray, reference_yaw_deg: np.ndarray) -> dict[str, float | int]:
    """Return the mean and SD (deg) of what the pose graph's edges measure of the relative yaw minus the tracker's,
    for the loop closures and the other edges apart, how many of each were compared, and the SD of those errors in
    units of the SD the graph weighs each edge's yaw with (`*_yaw_z_sd`: 1 where the graph weighs them as they are);
    with the edges' loads, also the mean over the loop closures whose frames' mean load lies in the top third of the
    compared closures' (`loop_yaw_bias_high_load_deg`, of `loop_high_load_edges`).

    edge_yaws: (E, 5) or (E, 6) rows of frame i, frame j, measured yaw of j relative to i (deg), loop 0/1, the yaw's
    SD in the graph (deg) and the mean load of the two frames (N) (SessionReconstruction.edge_yaws);
    reference_yaw_deg: (N,) the tracker's yaw per frame index, NaN where unknown.
    A bias the graph cannot average out turns the whole path (AccuracyReport.global_error's turn): an edge kind whose
    mean is off by a hundredth of a degree over hundreds of edges is where to look; an edge kind whose z SD is far
    above the others' pulls the yaws harder than its evidence warrants; a loop bias that grows with the load is where
    to look next (docs/accuracy.md, Known limits).
    """
    rows = np.asarray(edge_yaws, np.float64)
    ref = np.asarray(reference_yaw_deg, np.float64).ravel()
    i, j = rows[:, 0].astype(int), rows[:, 1].astype(int)
    inside = (i >= 0) & (j >= 0) & (i < len(ref)) & (j < len(ref))
    diff = np.full(len(rows), np.nan)
    diff[inside] = rows[inside, 2] - (ref[j[inside]] - ref[i[inside]])
    diff = (diff + 180.0) % 360.0 - 180.0
    out: dict[str, float | int] = {}
    for kind, chosen in (("loop", rows[:, 3] > 0), ("other", rows[:, 3] <= 0)):
        kept = chosen & np.isfinite(diff)
        valid = diff[kept]
        out[f"{kind}_edges"] = len(valid)
        out[f"{kind}_yaw_bias_deg"] = float(np.mean(valid)) if len(valid) else math.nan
        out[f"{kind}_yaw_sd_deg"] = float(np.std(valid)) if len(valid) else math.nan
        out[f"{kind}_yaw_z_sd"] = float(np.std(valid / rows[kept, 4])) if len(valid) else math.nan
    if rows.shape[1] >= 6:
        loops = (rows[:, 3] > 0) & np.isfinite(diff)
        high = loops & (rows[:, 5] >= np.quantile(rows[loops, 5], HIGH_LOAD_QUANTILE)) if loops.any() else loops
        out["loop_high_load_edges"] = int(np.count_nonzero(high))
        out["loop_yaw_bias_high_load_deg"] = float(np.mean(diff[high])) if high.any() else math.nan
    return out
