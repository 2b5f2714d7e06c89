"""Service configuration from the environment (prefix VEINMOSAIC_, plus REDIS_URL); read once at start-up."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import AliasChoices, Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.core.image_header import DEFAULT_MAX_FRAME_SIDE

Scope = Literal["ingest", "view", "admin"]


class Settings(BaseSettings):
    """All knobs of the HTTP service; tests build one explicitly, the server calls `get_settings()`.

    Note: pydantic-settings deep-merges dict fields from the environment into explicit values, so a test
    building Settings(api_keys=...) must clear VEINMOSAIC_API_KEYS from its environment.
    """

    model_config = SettingsConfigDict(env_prefix="VEINMOSAIC_", extra="ignore", populate_by_name=True)

    data_dir: Path = Path("./data")
    redis_url: str | None = Field(
        default=None, validation_alias=AliasChoices("REDIS_URL", "VEINMOSAIC_REDIS_URL", "redis_url")
    )
    redis_prefix: str = "vm:"
    api_keys: dict[str, list[Scope]] = Field(default_factory=dict, repr=False)
    token_secret: SecretStr | None = None
    max_frame_bytes: int = Field(default=20 * 1024 * 1024, gt=0)
    max_force_samples: int = Field(default=100_000, gt=0)
    # every other body (JSON, reference.csv), counted while it is read; 8 MiB holds 100k force rows
    max_json_bytes: int = Field(default=8 * 1024 * 1024, gt=0)
    # frames (and calibrations' image_size) at most this many pixels a side; see services/core/image_header.py
    max_frame_side: int = Field(default=DEFAULT_MAX_FRAME_SIDE, ge=16, le=16384)
    max_session_span_s: float = Field(default=86_400.0, gt=0)  # timestamps within this of the session's first
    min_free_mb: int = Field(default=200, ge=0)  # /readyz is 503 while the data volume has less free space
    audit_coalesce_s: float = Field(default=60.0, ge=0)  # repeated reads by one caller: one audit record per window
    queue_max_depth: int = Field(default=5000, gt=0)
    retry_after_s: int = Field(default=2, gt=0)
    viewer_token_ttl_s: int = Field(default=8 * 3600, gt=0)
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
    log_level: str = "INFO"
    viewer_assets_dir: Path | None = None  # OpenSeadragon build folder; default: the wheel's copy, else node_modules


def get_settings() -> Settings:
    """Return the settings read from the environment (call once, at start-up)."""
    return Settings()
