"""Options of a results version: {"method": name, "method_options": {...}, "calibration": {...overrides}}.

Error messages name the option and the constraint only, never a submitted value nor an unknown key (either
could carry patient data): they reach 422 answers, job records and logs.
"""

from __future__ import annotations

import math
import re
from dataclasses import fields
from typing import Any

from services.core.calibration import Calibration, CalibrationError
from services.core.features import FEATURE_KINDS
from services.core.methods import METHOD_NAMES, REGISTRATION_KINDS, MethodOptions, method_options

USER_KEYS = ("method", "method_options", "calibration")
SYSTEM_KEYS = ("source", "job")  # written by the workers into options.json


def _check_override_types(base: MethodOptions, overrides: dict[str, Any]) -> None:
    known = {f.name: getattr(base, f.name) for f in fields(base)}
    for name, value in overrides.items():
        if name == "name":
            raise ValueError("method_options: 'name' cannot be overridden; use 'method'")
        if name not in known:
            raise ValueError(f"method_options: unknown option; expected some of {', '.join(sorted(known))}")
        default = known[name]
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif isinstance(default, float):
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        else:
            ok = isinstance(value, type(default))
        if not ok:
            raise ValueError(f"method_options: {name} must be a {type(default).__name__}")


def parse_options(doc: Any, strict: bool = True) -> tuple[MethodOptions, dict[str, Any]]:
    """Return (method options, calibration overrides) of an options document; ValueError naming the field.

    strict=True (a client's document) rejects keys other than method, method_options, calibration.
    """
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise ValueError("options must be a JSON object")
    allowed = USER_KEYS if strict else USER_KEYS + SYSTEM_KEYS
    unknown = sorted(set(doc) - set(allowed))
    if unknown:
        raise ValueError(f"options: unknown field(s); expected some of {', '.join(USER_KEYS)}")
    name = doc.get("method", "best")
    if not isinstance(name, str):
        raise ValueError("options.method must be a string")
    if name not in METHOD_NAMES:
        raise ValueError(f"options.method: unknown method; expected one of {', '.join(METHOD_NAMES)}")
    opts = method_options(name)
    overrides = doc.get("method_options") or {}
    if not isinstance(overrides, dict):
        raise ValueError("options.method_options must be an object")
    _check_override_types(opts, overrides)
    opts = opts.with_overrides(
        {k: (float(v) if isinstance(getattr(opts, k), float) else v) for k, v in overrides.items()}
    )
    calib = doc.get("calibration") or {}
    if not isinstance(calib, dict):
        raise ValueError("options.calibration must be an object of calibration.json fields")
    return opts, dict(calib)


# the tail of a message that quotes the submitted value ("..., got -2"), and a list of unknown keys
_QUOTED_VALUE = re.compile(r",? got .*$", re.DOTALL)
_UNKNOWN_KEYS = re.compile(r"^(unknown field\(s\)):.*$", re.DOTALL)


def without_values(message: str) -> str:
    """Return a validation message with any quoted submitted value or unknown key name cut out."""
    message = _UNKNOWN_KEYS.sub(lambda m: f"{m.group(1)}; see the calibration.json fields (spec §3)", message)
    return _QUOTED_VALUE.sub("", message)


def apply_calibration(base: Calibration, overrides: dict[str, Any]) -> Calibration:
    """Return the calibration with overrides applied and validated (CalibrationError names the field only)."""
    if not overrides:
        return base
    try:
        return base.with_overrides(**overrides)
    except CalibrationError as exc:
        raise CalibrationError(without_values(str(exc))) from None


FIXED_CALIBRATION = ("image_size",)  # the stored frames have this size: it cannot be overridden
NON_NEGATIVE = ("ransac_px", "ratio", "max_jump_mm", "blur_ratio", "min_inliers", "neighbours", "loop_gap")


def validate_options(doc: Any, base: Calibration | None = None) -> dict[str, Any]:
    """Return the normalised options document of a client's reprocess request; the one validation of it.

    Raises ValueError naming the field (method, an option, a fixed calibration field), CalibrationError for a
    calibration override that does not apply to `base`; no message quotes a submitted value.
    """
    opts, calib = parse_options(doc, strict=True)
    if opts.features not in FEATURE_KINDS:
        raise ValueError(f"method_options: features must be one of {', '.join(FEATURE_KINDS)}")
    if opts.registration not in REGISTRATION_KINDS:
        raise ValueError(f"method_options: registration must be one of {', '.join(REGISTRATION_KINDS)}")
    for name in NON_NEGATIVE:
        value = getattr(opts, name)
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"method_options: {name} must be a finite number >= 0")
    if opts.max_features < 0:
        raise ValueError("method_options: max_features must be >= 0")
    for name in FIXED_CALIBRATION:
        if name in calib:
            raise ValueError(f"calibration.{name}: cannot be changed (the stored frames fix it)")
    if base is not None:
        apply_calibration(base, calib)
    out: dict[str, Any] = {"method": opts.name}
    if (doc or {}).get("method_options"):
        out["method_options"] = dict(doc["method_options"])
    if calib:
        out["calibration"] = calib
    return out
