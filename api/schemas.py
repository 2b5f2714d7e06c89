"""Request and response bodies of the v1 API (spec §5); unknown fields are rejected (422)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StrictInt

from services.core.inputs.study import STUDY_FIELDS, StudyContext, parse_study
from services.core.method_options import MethodOverrides
from services.core.methods import METHOD_NAMES
from services.store.storage import MAX_SEQ

# A JSON number that is finite: NaN/Infinity literals (which Python's json accepts) are rejected, and so are
# strings and booleans (no lax coercion of "1.5" or true).
Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Positive = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]
# Device time in seconds. 1e10 s admits a device clock counting Unix seconds (until 2286) as well as an uptime
# clock, and refuses absurd values (-1e308); plausibility against the session's own first timestamps (within
# max_session_span_s, a setting: 24 h) is checked when the upload is stored (409 implausible_timestamp).
MAX_ABS_TIME_S = 1e10
DeviceTime = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-MAX_ABS_TIME_S, le=MAX_ABS_TIME_S)]
# A hand-held probe's sensors read tens of newtons; 10 kN bounds a reading and keeps the force model finite.
Force = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-1e4, le=1e4)]
TiltDeg = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-360, le=360)]
ForceRow = tuple[DeviceTime, Force, Force, Force, Force]
ImuRow = tuple[DeviceTime, TiltDeg, TiltDeg]
Zero = Annotated[float, Field(strict=True, ge=0, le=0)]  # 0 or 0.0, never false
One = Annotated[float, Field(strict=True, ge=1, le=1)]


def _integral(value: Any) -> Any:
    """Return an integral float (640.0: an integer in JSON Schema) as an int; anything else unchanged."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


# image_size: whole pixels; the upper bound is the max_frame_side setting (api.app writes it into the schema).
# Field before the validator: the other order puts raw `ge`/`le` (not JSON Schema) into the schema, which then
# stated no bound at all, so sides below 16 were valid by the schema and 422 by the code.
Side = Annotated[int, Field(strict=True, ge=16, le=16384), BeforeValidator(_integral)]
Coefficients = (
    Annotated[list[Finite], Field(min_length=4, max_length=4)]
    | Annotated[list[Finite], Field(min_length=5, max_length=5)]
    | Annotated[list[Finite], Field(min_length=8, max_length=8)]
    | Annotated[list[Finite], Field(min_length=12, max_length=12)]
    | Annotated[list[Finite], Field(min_length=14, max_length=14)]
)


class Strict(BaseModel):
    """Base of every body: unknown fields are an error."""

    model_config = ConfigDict(extra="forbid")


CameraMatrix = tuple[tuple[Positive, Zero, Finite], tuple[Zero, Positive, Finite], tuple[Zero, Zero, One]]


class CalibrationDoc(Strict):
    """calibration.json (spec §3) as the API accepts it; core.physics.calibration.parse_calibration checks the same."""

    image_size: tuple[Side, Side] = Field(description="frame width, height in pixels")
    camera_matrix: CameraMatrix = Field(description="[[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels")
    px_per_mm: Positive
    dist_coeffs: Coefficients | None = Field(default=None, description="OpenCV order k1, k2, p1, p2[, k3, ...]")
    young_modulus_kpa: Positive | None = None
    poisson_ratio: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=0.5)] | None = None
    hooke_n_per_mm: Positive | None = None
    sensor_separation_mm: tuple[Positive, Positive] | None = None
    scanner_area_m2: Positive | None = None

    def document(self) -> dict[str, Any]:
        """Return the calibration.json document (fields left out take the spec's defaults)."""
        return self.model_dump(mode="json", exclude_none=True)


def _study_field(name: str, description: str, **constraints: Any) -> Any:
    return Field(
        default=None,
        max_length=STUDY_FIELDS[name][1] * (3 if name.endswith(("name", "physician")) else 1),
        description=description,
        **constraints,
    )


class StudyDoc(Strict):
    """The study context (spec §5): patient data, every field optional; core.inputs.study.parse_study checks it."""

    patient_id: str | None = _study_field("patient_id", "the hospital's patient id")
    patient_name: str | None = _study_field("patient_name", "DICOM person name, 'Family^Given'")
    patient_birth_date: str | None = _study_field("patient_birth_date", "YYYY-MM-DD", pattern=r"^\d{4}-\d{2}-\d{2}$")
    patient_sex: Literal["M", "F", "O"] | None = None
    accession_number: str | None = _study_field("accession_number", "the order's accession number")
    laterality: Literal["L", "R"] | None = Field(default=None, description="which breast: L or R")
    referring_physician: str | None = _study_field("referring_physician", "DICOM person name")
    study_description: str | None = _study_field("study_description", "free text")

    def context(self) -> StudyContext | None:
        """Return the validated StudyContext (None when nothing was given); raise StudyContextError."""
        return parse_study(self.model_dump(exclude_none=True))


class SessionCreate(Strict):
    """POST /v1/sessions body; the label and the study may identify a patient: stored, never logged."""

    calibration: CalibrationDoc
    label: str = Field(default="", max_length=256)
    study: StudyDoc | None = None


class SessionCreated(Strict):
    """201 answer: the session id, a signed view-only viewer link and its expiry (Unix s)."""

    id: str
    viewer_url: str
    viewer_token: str
    viewer_token_expires: int


class SessionState(Strict):
    """GET /v1/sessions/{id}: status, frame counters (processed includes lost) and the mosaic extent (mm)."""

    id: str
    status: Literal["receiving", "processing", "done", "failed"]
    label: str | None = None
    # the study context: to the owner's key and admins only, never via a viewer link
    study: dict[str, str] | None = None
    created: float
    finished: bool
    frames_received: int
    frames_processed: int
    frames_lost: int
    frames_rejected: int = 0  # of the results served: frames rejected (blur, implausible jump, bad frame)
    registered_fraction: float | None = None  # of the results served: frames placed / path rows
    not_placed_reasons: dict[str, int] = Field(default_factory=dict)  # lost + rejected frames per reason
    warnings: list[dict[str, str]] = Field(default_factory=list)  # [{"code", "message"}]: >5 % lost, failed, reprocess
    # while live: upload-to-placement lag of the newest placed frames {"p50_s", "p95_s", "frames"}; null when done
    lag: dict[str, float | int] | None = None
    extent: dict[str, Any] | None = None
    tissue: dict[str, Any] | None = None  # of the results served: what the scan taught (mosaic.json "tissue")


class FrameMeta(Strict):
    """The `meta` JSON part of a frame upload: seq (0..999999) and device time t_s in seconds."""

    seq: StrictInt = Field(ge=0, le=MAX_SEQ)
    t_s: DeviceTime


class FrameAccepted(Strict):
    """Answer to a frame upload: 202 "accepted" (stored and queued) or 200 "duplicate" (no-op)."""

    seq: int
    status: Literal["accepted", "duplicate"]


class ForceBatch(Strict):
    """POST /v1/sessions/{id}/forces body: rows [t_s, F1..F4 N] and optional IMU rows [t_s, tx, ty deg]."""

    samples: list[ForceRow]
    imu: list[ImuRow] | None = None


class ForcesAccepted(Strict):
    """202 answer to a force batch: how many samples and IMU rows were stored."""

    accepted: int
    imu_accepted: int


class Accepted(Strict):
    """202 answer to finish: the new status."""

    id: str
    status: str


class Health(Strict):
    """/healthz and /readyz answer."""

    status: Literal["ok"]
    checks: dict[str, bool] = Field(default_factory=dict)


# ----- results, reprocess and jobs (issue 3) ---------------------------------------------------------------------


# "method_options" is services.core.method_options.MethodOverrides: the one validator of method options (the
# workers and the CLI use it too): strict types, ranges, unknown options refused
MethodOptionsDoc = MethodOverrides


class CalibrationOverrides(Strict):
    """Calibration fields a reprocess may change (not image_size: the stored frames fix it)."""

    camera_matrix: CameraMatrix | None = None
    px_per_mm: Positive | None = None
    dist_coeffs: Coefficients | None = None
    young_modulus_kpa: Positive | None = None
    poisson_ratio: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=0.5)] | None = None
    hooke_n_per_mm: Positive | None = None
    sensor_separation_mm: tuple[Positive, Positive] | None = None
    scanner_area_m2: Positive | None = None


class ReprocessOptions(Strict):
    """The options of a results version: the method, overrides of its options, calibration overrides."""

    method: Literal[METHOD_NAMES] = "best"  # type: ignore[valid-type]
    method_options: MethodOptionsDoc | None = None  # type: ignore[valid-type]
    calibration: CalibrationOverrides | None = None

    def document(self) -> dict[str, Any]:
        """Return the options document the workers read (fields left out are not sent)."""
        return self.model_dump(mode="json", exclude_none=True)


class ReprocessRequest(Strict):
    """POST /v1/sessions/{id}/reprocess body: {"options": {"method", "method_options", "calibration"}}."""

    options: ReprocessOptions = Field(default_factory=ReprocessOptions)


class BatchReprocessRequest(Strict):
    """POST /v1/reprocess body: the sessions to reprocess (1..500, each visible to the key) and the options."""

    sessions: list[str] = Field(min_length=1, max_length=500)
    options: ReprocessOptions = Field(default_factory=ReprocessOptions)


class SendRequest(Strict):
    """POST /v1/sessions/{id}/send body: the name of a PACS destination the operator configured."""

    destination: str = Field(min_length=1, max_length=64, description="a name in VEINMOSAIC_PACS_DESTINATIONS")


class JobAccepted(Strict):
    """202 answer to a reprocess or send request: the job id and where to follow it."""

    job: str
    session: str
    status_url: str


class BatchAccepted(Strict):
    """202 answer to a batch reprocess request: the batch id and one job per session (in request order)."""

    batch: str
    jobs: list[str]
    status_url: str


JOB_STATUS = "queued, running, done or failed"
# `state` was a job's and a batch's name for what a session calls `status`: kept one release as an alias
DEPRECATED_STATE = "Deprecated alias of `status` (the same value), removed in the next release; read `status`."


class JobState(Strict):
    """GET /v1/jobs/{id}: kind, status queued|running|done|failed (`state`: its deprecated alias), progress
    done/total (frames for a reprocess, DICOM objects for a send), the results version; a send's attempts so far."""

    id: str
    kind: Literal["reprocess", "send"] = "reprocess"
    status: str = Field(description=JOB_STATUS)
    state: str = Field(description=DEPRECATED_STATE, deprecated=True)
    session: str
    version: int | None = None
    done: int = 0
    total: int = 0
    progress: float | None = None
    error: str | None = None
    created: float | None = None
    batch: str | None = None
    options: dict[str, Any] = Field(default_factory=dict)
    attempts: int = 0


class BatchState(Strict):
    """GET /v1/batches/{id}: the batch's jobs and an overall status (done when every job is done or failed), with
    `state` its deprecated alias."""

    batch: str
    status: str = Field(description=f"{JOB_STATUS}: done when every job is done or failed, failed if any failed")
    state: str = Field(description=DEPRECATED_STATE, deprecated=True)
    jobs: list[JobState]


# ----- audit log (issue 8) ------------------------------------------------------------------------------------------


class AuditRecord(BaseModel):
    """One audit record: who (actor), did what (action, route, method, status), to which session, when, whence."""

    ts: float
    actor: str
    action: str
    route: str
    method: str
    session: str | None = None
    status: int
    client: str | None = None
    request_id: str | None = None
    prev: str
    chain: str | None = Field(default=None, description='"hmac-sha256": hash is an HMAC with the audit key')
    hash: str


class AuditPage(Strict):
    """GET /v1/audit: matching records, newest first."""

    records: list[AuditRecord]
    count: int


class AuditVerification(Strict):
    """GET /v1/audit/verify: whether the keyed chain holds, how many records, and where it first breaks."""

    ok: bool
    records: int
    last_hash: str
    first_bad_line: int | None = None
    reason: str | None = None
    unkeyed: int = Field(default=0, description="records written before the chain was keyed (a prefix of the log)")
    files: int = Field(
        default=1, description="files of the chain checked: the rotated ones, oldest first, and the current"
    )
    first_bad_file: str | None = Field(default=None, description="the file (in the audit folder) of first_bad_line")
