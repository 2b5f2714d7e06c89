"""A worker's knobs and its shared handles (Redis client, raw store, results store)."""

from __future__ import annotations

import os
import socket
import threading
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import redis
from pydantic import Field, SecretBytes

from services.jobs import job_records as jobs
from services.pacs.destinations import Destination
from services.settings import Settings, WorkerSettings
from services.store.audit import AuditLog
from services.store.results_store import LIVE_VERSION, ResultsStore
from services.store.secrets import audit_key_bytes
from services.store.session_version import SessionVersion
from services.store.storage import SessionStore


def default_consumer() -> str:
    """Return the consumer name host:pid."""
    return f"{socket.gethostname()}:{os.getpid()}"


class WorkerConfig(WorkerSettings):
    """One worker process's configuration: the Settings' worker_config (WorkerSettings, its timings) plus where
    it works (data_dir, Redis URL and key prefix: the Settings' data_dir, redis_url, redis_prefix) and its
    consumer name. Made once at start-up by `from_settings`; validated like the Settings (unknown fields refused).
    """

    data_dir: Path
    redis_url: str | None = None
    prefix: str = "vm:"
    consumer: str = Field(default_factory=default_consumer)
    pacs_destinations: dict[str, Destination] = Field(default_factory=dict, repr=False)  # the Settings'
    pacs_timeout_s: float = Field(default=30.0, gt=0)
    jobs_in_flight: int = Field(default=8, ge=1)  # the Settings' queue_jobs_in_flight (job_lanes.admit)
    audit_max_bytes: int = Field(default=64 * 1024 * 1024, ge=0)  # the Settings' (services.store.audit rotation)
    audit_key: SecretBytes | None = Field(default=None, repr=False)  # the Settings' (None: from data_dir's settings)

    @classmethod
    def from_settings(cls, settings: Settings, **overrides: Any) -> WorkerConfig:
        """Return the configuration of a worker from the settings, with `overrides` (None: not overridden)."""
        doc: dict[str, Any] = {
            **settings.worker_config.model_dump(),
            "data_dir": settings.data_dir,
            "redis_url": settings.redis_url,
            "prefix": settings.redis_prefix,
            "pacs_destinations": settings.pacs_destinations,
            "pacs_timeout_s": settings.pacs_timeout_s,
            "jobs_in_flight": settings.queue_jobs_in_flight,
            "audit_max_bytes": settings.audit_max_bytes,
            "audit_key": audit_key_bytes(settings),
        }
        doc.update({k: v for k, v in overrides.items() if v is not None})
        return cls.model_validate(doc)


@dataclass
class Context:
    """What every stage uses: config, Redis, stores and the stop flag."""

    config: WorkerConfig
    r: redis.Redis
    store: SessionStore
    results: ResultsStore
    stop: threading.Event = field(default_factory=threading.Event)

    @property
    def prefix(self) -> str:
        """Return the Redis key prefix."""
        return self.config.prefix

    def version(self, sid: str, v: int = LIVE_VERSION) -> SessionVersion:
        """Return results version v of session sid (the live run's by default)."""
        return SessionVersion(self.store, self.results, sid, v)

    def update_job(self, job_id: str, **values: Any) -> None:
        """Set fields of a job's record (state, done, total, error, ...): services.jobs.job_records.update_job."""
        jobs.update_job(self.r, self.prefix, job_id, **values)

    def live_options(self) -> dict[str, str]:
        """Return the options a live version is made with: this worker's method and its options, if any."""
        options = {"method_options": dict(self.config.method_options)} if self.config.method_options else {}
        return {"method": self.config.method, **options, "source": "live"}

    @cached_property
    def audit(self) -> AuditLog:
        """Return the data directory's audit log (the API's, with its key; safe across processes on one host)."""
        key = self.config.audit_key
        secret = key.get_secret_value() if key is not None else audit_key_bytes(Settings(data_dir=self.config.data_dir))
        return AuditLog(self.config.data_dir / "audit" / "audit.jsonl", secret, self.config.audit_max_bytes)
