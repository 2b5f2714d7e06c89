"""A worker's knobs and its shared handles (Redis client, raw store, results store)."""

from __future__ import annotations

import os
import socket
import threading
from dataclasses import dataclass, field
from pathlib import Path

import redis

from services.store.results_store import ResultsStore
from services.store.storage import SessionStore


def default_consumer() -> str:
    """Return the consumer name host:pid."""
    return f"{socket.gethostname()}:{os.getpid()}"


@dataclass(frozen=True)
class WorkerConfig:
    """Timing and naming of one worker process; times in seconds unless the name says ms."""

    data_dir: Path
    redis_url: str | None = None
    prefix: str = "vm:"
    consumer: str = field(default_factory=default_consumer)
    method: str = "best"  # the live run's method (results version 1)
    lost_timeout_s: float = 10.0  # a missing frame is lost when a later one arrived this long ago
    lease_ms: int = 15_000  # registration lease; renewed while working
    claim_idle_ms: int = 30_000  # XAUTOCLAIM entries idle longer than this (a crashed worker's)
    claim_every_s: float = 5.0
    block_ms: int = 500  # XREADGROUP BLOCK when holding no session
    held_block_ms: int = 100  # ... when holding sessions (they are polled between reads)
    flush_every_s: float = 0.5  # path/tiles/mosaic.json/event at most this often
    image_every_s: float = 2.0  # whole mosaic.png/force.png at most this often (and at the end)
    max_deliveries: int = 3  # attempts before an entry goes to the dead-letter stream
    linger_s: float = 30.0  # release a session's lease after this long without progress
    pass_budget_s: float = 2.0  # registration work per pass before other duties get a turn
    not_ready_delay_s: float = 0.25  # re-schedule delay of a frame whose setup or forces are not there yet
    half_extent_mm: float = 200.0  # the Deep Zoom canvas: +-this around frame 0
    debug_order: bool = False  # log every frame handed to registration in <prefix>debug:order:<sid>:<v>
    fault_backoff_first_s: float = 0.1  # infrastructure faults (disk, Redis): first back-off ...
    fault_backoff_max_s: float = 5.0  # ... doubling up to this; a job is never dead-lettered for them
    reconcile_every_s: float = 60.0  # re-enqueue durable uploads with no job and no result (0: only at start)
    heartbeat_file: str | None = None  # touched every loop (at most every 2 s): a container health check


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
