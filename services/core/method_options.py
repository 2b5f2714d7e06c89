"""Options of a results version: {"method": name, "method_options": {...}, "calibration": {...overrides}}.

Error messages name the option and the constraint only, never a submitted value nor an unknown key (either
could carry patient data): they reach 422 answers, job records and logs.
"""

from __future__ import annotations

import re
from dataclasses import fields
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationError, create_model

from services.core.inputs.calibration import Calibration, CalibrationError
from services.core.methods import METHOD_NAMES, REGISTRATION_KINDS, MethodOptions, method_options
from services.core.registration.features import FEATURE_KINDS

USER_KEYS = ("method", "method_options", "calibration")
SYSTEM_KEYS = ("source", "job")  # written by the workers into options.json

MAX_COUNT = 100_000  # any whole-number option (min_inliers=100000 switches features off: docs/method.md)
# ranges beyond "a finite number >= 0" (floats) and "a whole number 0..MAX_COUNT" (ints). The counts that set a
# frame's cost (keypoints, neighbours matched, refinements) are held to what a frame can use, so one reprocess
# request cannot queue hours of work per frame
_BOUNDS: dict[str, dict[str, float]] = {
    "vein_scale": {"gt": 0, "le": 1},  # a fraction of full resolution
    "ratio": {"ge": 0, "le": 1},  # Lowe ratio
    "min_correlation": {"ge": 0, "le": 1},  # ECC correlation
    "track_overlap": {"ge": 0, "le": 1},  # a share of the keyframe's window
    "track_overlap_behind": {"ge": 0, "le": 1},  # the same, for a live session behind its uploads
    "track_correlation": {"ge": 0, "le": 1},  # ECC correlation
    "track_closures": {"ge": 0, "le": 20},  # direct alignments per tracked frame
    "confirmed_inlier_share": {"ge": 0, "le": 1},  # a share
    "blur_ratio": {"ge": 0, "le": 1},  # a fraction of the running median
    "contrast_threshold": {"ge": 0, "le": 1},  # SIFT's (0.03 by default)
    "scale_prior": {"ge": 0, "le": 1},  # a relative sigma
    "chain_scale_band": {"ge": 0, "le": 1},  # log of a scale
    "ransac_px": {"ge": 0, "le": 50},  # pixels of a rectified frame
    "loop_ransac_px": {"ge": 0, "le": 50},  # pixels of a rectified frame
    "drag_pair_gate": {"ge": 0, "le": 10},  # RANSAC gates
    "max_jump_mm": {"ge": 0, "le": 1000},  # a breast is smaller
    "max_features": {"ge": 0, "le": 20_000},  # SIFT's cap per view (0: no cap)
    "target_features": {"ge": 0, "le": 10_000},  # keypoints kept per frame
    "sift_finest_octave": {"ge": -1, "le": 0},  # -1 OpenCV's doubled image, 0 the image's own pixels
    "neighbours": {"ge": 0, "le": 32},  # keyframes matched per frame
    "refine_every": {"ge": 1, "le": MAX_COUNT},  # 0 would re-optimise the pose graph at every frame
}


def _overrides_model() -> type[BaseModel]:
    """Return the model of "method_options": every MethodOptions field but its name, optional, typed and bounded.

    Strict types (a bool is never a number, a number never a string), finite floats, unknown keys refused.
    """
    specs: dict[str, Any] = {}
    for f in fields(MethodOptions):
        default = f.default
        if f.name == "name":
            continue
        if f.name == "features":
            kind: Any = Literal[FEATURE_KINDS]  # type: ignore[valid-type]
        elif f.name == "registration":
            kind = Literal[REGISTRATION_KINDS]  # type: ignore[valid-type]
        elif isinstance(default, bool):
            kind = StrictBool
        elif isinstance(default, int):
            bounds = _BOUNDS.get(f.name, {"ge": 0, "le": MAX_COUNT})
            kind = Annotated[int, Field(strict=True, **bounds)]
        elif isinstance(default, float):
            bounds = _BOUNDS.get(f.name, {"ge": 0})
            kind = Annotated[float, Field(strict=True, allow_inf_nan=False, **bounds)]
        else:  # pragma: no cover - a new kind of option needs its type here
            raise TypeError(f"MethodOptions.{f.name}: no validation rule for {type(default).__name__}")
        specs[f.name] = (kind | None, None)
    return create_model(
        "MethodOverrides",
        __config__=ConfigDict(extra="forbid", frozen=True),
        __doc__="Overrides of a method's options (services.core.methods.MethodOptions), each optional.",
        **specs,
    )


# The one validator of method options: the API's request schema, the workers' options.json and the CLI's
# --option KEY=VALUE (lax mode: strings converted) all go through it.
MethodOverrides = _overrides_model()

_KINDS = {
    "bool_type": "a boolean",
    "int_type": "a whole number",
    "int_from_float": "a whole number",
    "int_parsing": "a whole number",
    "float_type": "a number",
    "float_parsing": "a number",
    "finite_number": "a finite number",
    "bool_parsing": "a boolean",
}
_BOUND_ERRORS = {
    "greater_than": ("gt", ">"),
    "greater_than_equal": ("ge", ">="),
    "less_than": ("lt", "<"),
    "less_than_equal": ("le", "<="),
}


def _constraint(error: dict[str, Any]) -> str:
    """Return the constraint a pydantic error broke, without the submitted value."""
    kind, ctx = error["type"], error.get("ctx") or {}
    if kind in _KINDS:
        return f"must be {_KINDS[kind]}"
    if kind == "literal_error":
        return f"must be one of {ctx.get('expected', '')}".rstrip()
    for bound, (name, word) in _BOUND_ERRORS.items():
        if kind == bound:
            return f"must be {word} {ctx.get(name)}"
    return "is invalid"


def check_overrides(overrides: Any, lax: bool = False) -> dict[str, Any]:
    """Return the method option overrides validated by MethodOverrides (only the fields given, floats as floats).

    lax=True converts strings (the CLI's KEY=VALUE). ValueError names the option and the constraint only.
    """
    if overrides is None:
        return {}
    if not isinstance(overrides, dict):
        raise ValueError("options.method_options must be an object")
    if "name" in overrides:
        raise ValueError("method_options: 'name' cannot be overridden; use 'method'")
    try:
        model = MethodOverrides.model_validate(overrides, strict=False if lax else None)
    except ValidationError as exc:
        error = exc.errors(include_input=False, include_url=False)[0]
        if error["type"] == "extra_forbidden":
            known = ", ".join(sorted(MethodOverrides.model_fields))
            raise ValueError(f"method_options: unknown option; expected some of {known}") from None
        field = ".".join(str(p) for p in error["loc"]) or "method_options"
        raise ValueError(f"method_options: {field} {_constraint(error)}") from None
    return model.model_dump(exclude_unset=True)


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
    opts = method_options(name).with_overrides(check_overrides(doc.get("method_options")))
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


def validate_options(doc: Any, base: Calibration | None = None) -> dict[str, Any]:
    """Return the normalised options document of a client's reprocess request; the one validation of it.

    Raises ValueError naming the field (method, an option, a fixed calibration field), CalibrationError for a
    calibration override that does not apply to `base`; no message quotes a submitted value.
    """
    opts, calib = parse_options(doc, strict=True)  # method options: MethodOverrides
    for name in FIXED_CALIBRATION:
        if name in calib:
            raise ValueError(f"calibration.{name}: cannot be changed (the stored frames fix it)")
    if base is not None:
        apply_calibration(base, calib)
    out: dict[str, Any] = {"method": opts.name}
    overrides = check_overrides((doc or {}).get("method_options"))
    if overrides:
        out["method_options"] = overrides
    if calib:
        out["calibration"] = calib
    return out
