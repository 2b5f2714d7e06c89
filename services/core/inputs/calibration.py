"""Probe calibration (spec §3 calibration.json): camera model, scale and force-model constants."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

KNOWN_FIELDS = frozenset(
    {
        "image_size",
        "camera_matrix",
        "dist_coeffs",
        "px_per_mm",
        "young_modulus_kpa",
        "poisson_ratio",
        "hooke_n_per_mm",
        "sensor_separation_mm",
        "scanner_area_m2",
    }
)
REQUIRED_FIELDS = ("image_size", "camera_matrix", "px_per_mm")


class CalibrationError(ValueError):
    """A calibration document that does not follow spec §3; the message names the field."""


@dataclass(frozen=True)
class Calibration:
    """Camera intrinsics (pixels), scale (px/mm) and the force model's constants (spec §2 units)."""

    image_size: tuple[int, int]
    camera_matrix: tuple[tuple[float, float, float], ...]
    px_per_mm: float
    dist_coeffs: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    young_modulus_kpa: float = 16.1
    poisson_ratio: float = 0.5
    hooke_n_per_mm: float = 18.0
    sensor_separation_mm: tuple[float, float] = (53.0, 53.0)
    scanner_area_m2: float = 0.0048
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def principal_point(self) -> tuple[float, float]:
        """Return (cx, cy) in pixels."""
        return float(self.camera_matrix[0][2]), float(self.camera_matrix[1][2])

    @property
    def K(self) -> np.ndarray:  # noqa: N802 (OpenCV naming)
        """Return the 3x3 camera matrix as float64."""
        return np.asarray(self.camera_matrix, dtype=np.float64)

    @property
    def D(self) -> np.ndarray:  # noqa: N802 (OpenCV naming)
        """Return the distortion coefficients as float64 (OpenCV order k1, k2, p1, p2[, k3...])."""
        return np.asarray(self.dist_coeffs, dtype=np.float64)

    @property
    def compliance_per_n(self) -> float:
        """Return nu / (E A) in 1/N: the fractional stretch per newton of local load (spec §2)."""
        return self.poisson_ratio / (self.young_modulus_kpa * 1000.0 * self.scanner_area_m2)

    def with_overrides(self, **changes: Any) -> Calibration:
        """Return a copy with the given fields replaced, validated like a parsed document."""
        doc = self.to_dict()
        doc.update(changes)
        return parse_calibration(doc)

    def to_dict(self) -> dict[str, Any]:
        """Return the calibration.json document (spec §3) for this calibration."""
        doc = asdict(self)
        doc.pop("extra", None)
        doc["image_size"] = list(self.image_size)
        doc["camera_matrix"] = [list(r) for r in self.camera_matrix]
        doc["dist_coeffs"] = list(self.dist_coeffs)
        doc["sensor_separation_mm"] = list(self.sensor_separation_mm)
        return doc


def _finite_number(doc: dict[str, Any], key: str, positive: bool = True) -> float:
    value = doc[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CalibrationError(f"{key}: expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise CalibrationError(f"{key}: must be > 0, got {value!r}")
    return float(value)


def _number_list(value: Any, key: str, length: int | None = None) -> list[float]:
    if not isinstance(value, list | tuple) or (length is not None and len(value) != length):
        want = f"a list of {length} numbers" if length else "a list of numbers"
        raise CalibrationError(f"{key}: expected {want}, got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise CalibrationError(f"{key}: every entry must be a finite number, got {v!r}")
        out.append(float(v))
    return out


def parse_calibration(doc: Any) -> Calibration:
    """Return a validated Calibration from a calibration.json document; raise CalibrationError naming the field."""
    if not isinstance(doc, dict):
        raise CalibrationError("calibration: expected a JSON object")
    unknown = sorted(set(doc) - KNOWN_FIELDS)
    if unknown:
        raise CalibrationError(f"unknown field(s): {', '.join(unknown)}")
    missing = [k for k in REQUIRED_FIELDS if k not in doc]
    if missing:
        raise CalibrationError(f"missing required field(s): {', '.join(missing)}")
    size = _number_list(doc["image_size"], "image_size", 2)
    if any(s != int(s) or s < 16 or s > 16384 for s in size):
        raise CalibrationError(f"image_size: expected two whole numbers of pixels (16..16384), got {size}")
    km = doc["camera_matrix"]
    if not isinstance(km, list | tuple) or len(km) != 3:
        raise CalibrationError("camera_matrix: expected a 3x3 list of lists")
    rows = [_number_list(r, "camera_matrix", 3) for r in km]
    # skew (K[0][1]) must be 0: the lens model (camera.py, like OpenCV's) uses fx, fy, cx, cy only
    if rows[0][0] <= 0 or rows[1][1] <= 0 or rows[2] != [0.0, 0.0, 1.0] or rows[1][0] != 0.0 or rows[0][1]:
        raise CalibrationError("camera_matrix: expected [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    kwargs: dict[str, Any] = {
        "image_size": (int(size[0]), int(size[1])),
        "camera_matrix": tuple(tuple(r) for r in rows),
        "px_per_mm": _finite_number(doc, "px_per_mm"),
    }
    if "dist_coeffs" in doc:
        d = _number_list(doc["dist_coeffs"], "dist_coeffs")
        if len(d) not in (4, 5, 8, 12, 14):
            raise CalibrationError(f"dist_coeffs: expected 4, 5, 8, 12 or 14 numbers, got {len(d)}")
        kwargs["dist_coeffs"] = tuple(d)
    for key in ("young_modulus_kpa", "hooke_n_per_mm", "scanner_area_m2"):
        if key in doc:
            kwargs[key] = _finite_number(doc, key)
    if "poisson_ratio" in doc:
        nu = _finite_number(doc, "poisson_ratio")
        if nu >= 0.5 + 1e-9 and nu != 0.5:
            raise CalibrationError(f"poisson_ratio: must be in (0, 0.5], got {nu}")
        kwargs["poisson_ratio"] = nu
    if "sensor_separation_mm" in doc:
        sep = _number_list(doc["sensor_separation_mm"], "sensor_separation_mm", 2)
        if min(sep) <= 0:
            raise CalibrationError("sensor_separation_mm: both separations must be > 0")
        kwargs["sensor_separation_mm"] = (sep[0], sep[1])
    return Calibration(**kwargs)


def default_calibration(width: int = 400, height: int = 320, px_per_mm: float = 8.0, **overrides: Any) -> Calibration:
    """Return a calibration with a centred principal point and the paper's force constants (for tests)."""
    f = 1.0 * max(width, height)
    base = Calibration(
        image_size=(width, height),
        camera_matrix=((f, 0.0, (width - 1) / 2.0), (0.0, f, (height - 1) / 2.0), (0.0, 0.0, 1.0)),
        px_per_mm=px_per_mm,
    )
    return replace(base, **overrides) if overrides else base
