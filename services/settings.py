"""Service configuration from the environment (prefix VEINMOSAIC_, plus REDIS_URL); read once at start-up.

One Settings object configures the API, the workers and the command line: each process reads it from its
environment once (`veinmosaic serve` starts its children with its own environment, so they read the same
values). A worker's timings are one JSON variable, VEINMOSAIC_WORKER_CONFIG (the `worker_config` field, a
WorkerSettings), parsed and checked by this model: unknown or mistyped fields stop the worker at start-up.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AliasChoices,
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from services.core.inputs.image_header import DEFAULT_MAX_FRAME_SIDE
from services.core.method_options import validate_options
from services.core.methods import METHOD_NAMES
from services.pacs.destinations import Destination, destinations_from_doc, parse_destinations

Scope = Literal["ingest", "view", "admin"]
# secrets shorter than these are refused at start-up (a short key or secret can be guessed offline from a
# fingerprint or a signed link); `python -c "import secrets; print(secrets.token_urlsafe(32))"` makes one
MIN_TOKEN_SECRET_CHARS = 32
MIN_API_KEY_CHARS = 24


class WorkerSettings(BaseModel):
    """Timing and switches of a worker process; times in seconds unless the name says ms.

    Set as one JSON object, VEINMOSAIC_WORKER_CONFIG='{"lost_timeout_s": 5}' (fields left out keep these
    defaults), or per field on `veinmosaic worker` (--config-json, --lost-timeout-s, --lease-ms, ...).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    method: Literal[METHOD_NAMES] = "best"  # type: ignore[valid-type]  # the live run's method (version 1)
    # ... and its method options, as a reprocess request gives them (e.g. {"track_overlap": 0.85}): checked once here
    method_options: dict[str, Any] = Field(default_factory=dict)
    lost_timeout_s: float = Field(default=10.0, ge=0)  # a missing frame is lost when a later one arrived this long ago
    lease_ms: int = Field(default=15_000, gt=0)  # registration lease; renewed while working
    claim_idle_ms: int = Field(default=30_000, ge=0)  # XAUTOCLAIM entries idle longer than this (a crashed worker's)
    claim_every_s: float = Field(default=5.0, gt=0)
    block_ms: int = Field(default=500, ge=0)  # XREADGROUP BLOCK when holding no session
    held_block_ms: int = Field(default=100, ge=0)  # ... when holding sessions (they are polled between reads)
    flush_every_s: float = Field(default=0.5, ge=0)  # path/tiles/mosaic.json/event at most this often
    behind_flush_every_s: float = Field(default=2.0, ge=0)  # ... while a live session is behind its uploads:
    # its newest published frame waited longer than this since upload: as track_lag_s, so a session whose frames are
    # tracked also flushes less often (three probes, at 1.5 against 5 s: 10.8-13.2 -> 7.0-8.7 ms of flushes a frame)
    behind_lag_s: float = Field(default=1.0, ge=0)
    # a live session whose newest published frame waited longer than this has its next frames prepared without
    # features, to be tracked on keyframes (MethodOptions.track_overlap_behind; issue 32; 0: never, as offline). 1.0
    # and 1.5 s taking turns, three probes (bench/probes.py): the slowest session done 4.5-4.7 s against 5.0-5.1 s
    track_lag_s: float = Field(default=1.0, ge=0)
    image_every_s: float = Field(default=2.0, ge=0)  # whole mosaic.png/force.png at most this often (and at the end)
    finish_ahead_every_s: float = Field(default=0.0, ge=0)  # a live session's finish run ahead this often (0: off)
    max_deliveries: int = Field(default=3, ge=1)  # attempts before an entry goes to the dead-letter stream
    linger_s: float = Field(default=30.0, ge=0)  # release a session's lease after this long without progress
    pass_budget_s: float = Field(default=2.0, gt=0)  # registration work per pass before other duties get a turn
    not_ready_delay_s: float = Field(default=0.25, ge=0)  # re-schedule delay of a frame whose setup/forces are missing
    half_extent_mm: float = Field(default=200.0, gt=0)  # the Deep Zoom canvas: +-this around frame 0
    debug_order: bool = False  # log every frame handed to registration in <prefix>debug:order:<sid>:<v>
    fault_backoff_first_s: float = Field(default=0.1, gt=0)  # infrastructure faults (disk, Redis): first back-off ...
    fault_backoff_max_s: float = Field(default=5.0, gt=0)  # ... doubling up to this; never dead-lettered for them
    reconcile_every_s: float = Field(default=60.0, ge=0)  # re-enqueue uploads with no job and no result (0: at start)
    job_busy_retry_s: float = Field(default=30.0, gt=0)  # a reprocess entry whose job runs in another worker waits
    heartbeat_file: str | None = None  # touched every loop (at most every 2 s): a container health check
    pacs_max_attempts: int = Field(default=8, ge=1)  # a send to an unreachable PACS: attempts before it fails
    pacs_retry_first_s: float = Field(default=5.0, gt=0)  # ... the wait after the first, doubling ...
    pacs_retry_max_s: float = Field(default=300.0, gt=0)  # ... up to this
    pacs_wait_s: float = Field(default=5.0, gt=0)  # a send job queued before its session is done looks again after

    @model_validator(mode="after")
    def _live_options_valid(self) -> WorkerSettings:
        """Refuse live method options a reprocess request would be refused (services.core.method_options)."""
        validate_options({"method": self.method, "method_options": self.method_options})
        return self


class Settings(BaseSettings):
    """All knobs of the HTTP service; tests build one explicitly, the server calls `get_settings()`.

    Note: pydantic-settings deep-merges dict fields from the environment into explicit values, so a test
    building Settings(api_keys=...) must clear VEINMOSAIC_API_KEYS from its environment.
    """

    # errors never echo an input: API keys, the token secret and PACS headers are secrets
    model_config = SettingsConfigDict(
        env_prefix="VEINMOSAIC_", extra="ignore", populate_by_name=True, hide_input_in_errors=True
    )

    data_dir: Path = Path("./data")
    redis_url: str | None = Field(  # not in the repr: it may carry Redis's password
        default=None, validation_alias=AliasChoices("REDIS_URL", "VEINMOSAIC_REDIS_URL", "redis_url"), repr=False
    )
    redis_prefix: str = "vm:"
    api_keys: dict[str, list[Scope]] = Field(default_factory=dict, repr=False)
    token_secret: SecretStr | None = None
    # rotation: tokens signed with these older secrets still verify until they expire (new ones use token_secret);
    # JSON list in VEINMOSAIC_PREVIOUS_TOKEN_SECRETS, dropped once the longest token lifetime has passed
    previous_token_secrets: list[SecretStr] = Field(default_factory=list, repr=False)
    # keys the audit log's chain and the key ids in its records; unset: derived from the token secret
    audit_secret: SecretStr | None = None
    max_frame_bytes: int = Field(default=20 * 1024 * 1024, gt=0)
    max_force_samples: int = Field(default=100_000, gt=0)
    # every other body (JSON, reference.csv), counted while it is read; 8 MiB holds 100k force rows
    max_json_bytes: int = Field(default=8 * 1024 * 1024, gt=0)
    # frames (and calibrations' image_size) at most this many pixels a side; see services/core/inputs/image_header.py
    max_frame_side: int = Field(default=DEFAULT_MAX_FRAME_SIDE, ge=16, le=16384)
    max_session_span_s: float = Field(default=86_400.0, gt=0)  # timestamps within this of the session's first
    min_free_mb: int = Field(default=200, ge=0)  # /readyz is 503 while the data volume has less free space
    audit_coalesce_s: float = Field(default=60.0, ge=0)  # repeated reads by one caller: one audit record per window
    # audit.jsonl is rotated to audit-000001.jsonl, ... before a record would take it past this; the keyed chain runs
    # on across the files (services/store/audit.py); 0: never rotated
    audit_max_bytes: int = Field(default=64 * 1024 * 1024, ge=0)
    # per-client rate limits (token buckets, per API process; 429 with Retry-After beyond; a burst of 0: no limit).
    # Requests without a valid credential, per client address: a flood is refused before it costs a disk write
    rate_limit_anonymous_per_s: float = Field(default=20.0, gt=0)
    rate_limit_anonymous_burst: int = Field(default=200, ge=0)
    # the expensive reads (export.dcm?layer=report, sheet.pdf/png, GET /report), per client address and caller
    rate_limit_expensive_per_s: float = Field(default=0.5, gt=0)
    rate_limit_expensive_burst: int = Field(default=30, ge=0)
    # open event streams (SSE) per API process: per caller (key or viewer link; 429 beyond) and in all (503 beyond)
    events_max_per_principal: int = Field(default=16, ge=1)
    events_max_total: int = Field(default=256, ge=1)
    # how long a browser may keep a versioned Deep Zoom tile (private: never in a shared cache)
    tile_cache_max_age_s: int = Field(default=300, ge=0)
    queue_max_depth: int = Field(default=5000, gt=0)
    # open (queued or running) reprocess and send jobs per API key; beyond, 429 quota_exceeded with Retry-After, so
    # one key cannot fill the queue (queue_max_depth) and make every other key's jobs answer 503
    queue_max_jobs_per_key: int = Field(default=1000, gt=0)
    # fair queueing (services/jobs/job_lanes.py): reprocess and send jobs wait in one lane per key and are admitted
    # round-robin onto the workers' job stream while it holds fewer than this (queued there or running), so one
    # key's flood delays another key's job by at most this many jobs; at least the number of worker processes
    queue_jobs_in_flight: int = Field(default=8, ge=1)
    # per-key quotas (services/jobs/quotas.py): sessions created and new frames uploaded by one API key in each
    # fixed window of quota_window_s, shared by every API process (Redis); beyond, 429 quota_exceeded with
    # Retry-After (the window's end) while other keys go on; 0: no limit. A probe at 10 frames/s makes 36000 an hour
    quota_window_s: int = Field(default=3600, ge=1)
    quota_sessions_per_key: int = Field(default=200, ge=0)
    quota_frames_per_key: int = Field(default=200_000, ge=0)
    retry_after_s: int = Field(default=2, gt=0)
    viewer_token_ttl_s: int = Field(default=2 * 3600, gt=0)  # a viewing session's link, not a working day's
    # `veinmosaic serve` supervision: a dead child (API, worker, embedded Redis) is restarted after
    # restart_first_s, doubling per consecutive short-lived run up to restart_max_s; a child that has run
    # healthy_after_s counts as healthy again (back to the first delay)
    restart_first_s: float = Field(default=0.5, gt=0)
    restart_max_s: float = Field(default=30.0, gt=0)
    healthy_after_s: float = Field(default=30.0, gt=0)
    # uvicorn worker processes of the API under `veinmosaic serve` (one process is bound by its GIL)
    api_workers: int = Field(default=1, ge=1, le=32)
    # workers lower their CPU priority by this much (os.nice) so uploads and tiles win a busy CPU; processing
    # catches up when the burst is over (0: equal priority)
    worker_nice: int = Field(default=10, ge=0, le=19)
    # OpenCV threads in each worker process: the parallelism is across worker processes (and sessions), and on a
    # small machine OpenCV's own threads only add overhead (SIFT 25 % more CPU per frame with 2 threads)
    worker_cv_threads: int = Field(default=1, ge=1, le=64)
    # the workers' timings: VEINMOSAIC_WORKER_CONFIG, one JSON object of WorkerSettings fields
    worker_config: WorkerSettings = Field(default_factory=WorkerSettings)
    # `veinmosaic serve` (and demo): the API's interface and port, and how many worker processes it starts
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)
    workers: int = Field(default=2, ge=0, le=64)
    log_level: str = "INFO"
    # GET /openapi.json: to callers with a valid API key ("keys"), to anyone ("public"), or not at all ("off", for
    # production); the interactive /docs and /redoc pages (scripts from a CDN) are never served
    api_docs: Literal["keys", "public", "off"] = "keys"
    viewer_assets_dir: Path | None = None  # OpenSeadragon build folder; default: the wheel's copy, else node_modules
    # PACS destinations (spec §5), the operator's: VEINMOSAIC_PACS_DESTINATIONS, one JSON object of named
    # destinations, {"<name>": {"dicomweb": "<base URL>"}} or {"<name>": {"dimse": {"host", "port", "called_ae",
    # "calling_ae"}}}; checked at start-up (services/pacs/destinations.py). Not in the repr: headers are secrets
    pacs_destinations: Annotated[dict[str, Destination], NoDecode] = Field(default_factory=dict, repr=False)
    pacs_timeout_s: float = Field(default=30.0, gt=0)  # a send's connect, each answer and each write wait this long
    # destinations every session is sent to once it is done (the send job is queued when the session is finished)
    pacs_auto_send: list[str] = Field(default_factory=list)

    @field_validator("api_keys")
    @classmethod
    def _keys_long_enough(cls, value: dict[str, list[Scope]]) -> dict[str, list[Scope]]:
        """Refuse an API key shorter than MIN_API_KEY_CHARS (the message names its scopes, never the key)."""
        for key, scopes in value.items():
            if len(key) < MIN_API_KEY_CHARS:
                raise ValueError(
                    f"an API key (scopes {', '.join(scopes) or 'none'}) has {len(key)} characters; at least "
                    f"{MIN_API_KEY_CHARS} are required (make one with secrets.token_urlsafe(32))"
                )
        return value

    @field_validator("token_secret", "audit_secret", "previous_token_secrets")
    @classmethod
    def _secret_long_enough(
        cls, value: SecretStr | list[SecretStr] | None, info: ValidationInfo
    ) -> SecretStr | list[SecretStr] | None:
        """Refuse a secret shorter than MIN_TOKEN_SECRET_CHARS (the token secret unset: data_dir/secret is made)."""
        for secret in value if isinstance(value, list) else [value]:
            if secret is not None and len(secret.get_secret_value()) < MIN_TOKEN_SECRET_CHARS:
                raise ValueError(
                    f"VEINMOSAIC_{str(info.field_name).upper()} has a secret of {len(secret.get_secret_value())} "
                    f"characters; at least {MIN_TOKEN_SECRET_CHARS} are required (make one with "
                    "secrets.token_urlsafe(32))"
                )
        return value

    @field_validator("pacs_destinations", mode="before")
    @classmethod
    def _parse_pacs_destinations(cls, value: object) -> object:
        """Parse the JSON text of the environment (or a dict given in code) into destinations."""
        if isinstance(value, str):
            return parse_destinations(value)
        if isinstance(value, dict) and not all(isinstance(v, Destination) for v in value.values()):
            return destinations_from_doc(value)
        return value

    @model_validator(mode="after")
    def _auto_send_destinations_exist(self) -> Settings:
        """Refuse an auto-send destination that is not configured (at start-up, not at the first send)."""
        unknown = sorted(set(self.pacs_auto_send) - set(self.pacs_destinations))
        if unknown:
            raise ValueError(f"pacs_auto_send: not in pacs_destinations: {', '.join(unknown)}")
        return self


def get_settings() -> Settings:
    """Return the settings read from the environment (call once, at start-up)."""
    return Settings()
