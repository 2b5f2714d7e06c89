"""Request and response bodies of the v1 API (spec §5); unknown fields are rejected (422)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt

from services.storage import MAX_SEQ

# A JSON number that is finite: NaN/Infinity literals (which Python's json accepts) are rejected, and so are
# strings and booleans (no lax coercion of "1.5" or true).
Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]
ForceRow = Annotated[list[Finite], Field(min_length=5, max_length=5)]
ImuRow = Annotated[list[Finite], Field(min_length=3, max_length=3)]


class Strict(BaseModel):
    """Base of every body: unknown fields are an error."""

    model_config = ConfigDict(extra="forbid")


class SessionCreate(Strict):
    """POST /v1/sessions body; the label may identify a patient: stored, never logged."""

    calibration: dict[str, Any]
    label: str = Field(default="", max_length=256)


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
    created: float
    finished: bool
    frames_received: int
    frames_processed: int
    frames_lost: int
    extent: dict[str, Any] | None = None


class FrameMeta(Strict):
    """The `meta` JSON part of a frame upload: seq (0..999999) and device time t_s in seconds."""

    seq: StrictInt = Field(ge=0, le=MAX_SEQ)
    t_s: Finite


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


class ReprocessRequest(Strict):
    """POST /v1/sessions/{id}/reprocess body: {"options": {"method": ..., <method options>, "calibration": {...}}}."""

    options: dict[str, Any] = Field(default_factory=dict)


class BatchReprocessRequest(Strict):
    """POST /v1/reprocess body: the sessions to reprocess (1..500, each visible to the key) and the options."""

    sessions: list[str] = Field(min_length=1, max_length=500)
    options: dict[str, Any] = Field(default_factory=dict)


class JobAccepted(Strict):
    """202 answer to a reprocess request: the job id and where to follow it."""

    job: str
    session: str
    status_url: str


class BatchAccepted(Strict):
    """202 answer to a batch reprocess request: the batch id and one job per session (in request order)."""

    batch: str
    jobs: list[str]
    status_url: str


class JobState(Strict):
    """GET /v1/jobs/{id}: state queued|running|done|failed, progress done/total frames, the results version."""

    id: str
    state: str
    session: str
    version: int | None = None
    done: int = 0
    total: int = 0
    progress: float | None = None
    error: str | None = None
    created: float | None = None
    batch: str | None = None
    options: dict[str, Any] = Field(default_factory=dict)


class BatchState(Strict):
    """GET /v1/batches/{id}: the batch's jobs and an overall state (done when every job is done or failed)."""

    batch: str
    state: str
    jobs: list[JobState]
