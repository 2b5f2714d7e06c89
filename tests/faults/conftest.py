"""Fault-injection fixtures: a private redis-server with AOF (killable, restartable), real worker processes,
an uploader that behaves like the API plus a retrying client, and the delivery check every fault test ends
with (every accepted frame processed exactly once: lost = 0, duplicated = 0)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import redis

from cli.launcher import free_port, serve_command, service_env, start_process, stop_processes
from services.core.inputs.scan import Scan
from services.jobs import queue
from services.store.results_store import LIVE_VERSION, ResultsStore
from services.store.storage import SessionStore

REPO = Path(__file__).resolve().parents[2]
REDIS_SERVER = shutil.which("redis-server") or "/usr/bin/redis-server"
PREFIX = "vm:"
# fast leases and claims so take-overs happen within a test's seconds; short back-offs
FAST: dict[str, Any] = {
    "lease_ms": 4000,  # the machine may be loaded: a lease must outlive a slow pass
    "claim_idle_ms": 4000,
    "claim_every_s": 0.5,
    "flush_every_s": 0.3,
    "image_every_s": 1.0,
    "linger_s": 5.0,
    # a test stores its frames before (or while) the worker runs, so they all wait: tracking the frames of a session
    # behind its uploads (issue 32) would make the live path differ from the offline one these tests compare it with;
    # test_live_pipeline's own test turns it on
    "track_lag_s": 0.0,
    "fault_backoff_first_s": 0.1,
    "fault_backoff_max_s": 1.0,
    "reconcile_every_s": 3.0,
}


@dataclass
class RedisServer:
    """A redis-server of our own on a free port, appendonly yes (fsync every second), data in `dir`."""

    dir: Path
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        """Return the server's URL."""
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        """Start the server (loading its AOF when there is one) and wait until it answers PING."""
        self.dir.mkdir(parents=True, exist_ok=True)
        cmd = [
            REDIS_SERVER, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.dir),
            "--appendonly", "yes", "--appendfsync", "everysec", "--save", "", "--protected-mode", "no",
        ]  # fmt: skip
        log = open(self.dir / "redis.log", "ab")  # noqa: SIM115 (kept open for the process)
        self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        client = redis.Redis(port=self.port, socket_connect_timeout=0.5)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            with contextlib.suppress(redis.RedisError):
                if client.ping():
                    client.close()
                    return
            time.sleep(0.05)
        raise RuntimeError("redis-server did not start")

    def kill(self) -> None:
        """SIGKILL the server (no shutdown save: what survives is what the AOF had fsynced)."""
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait()

    def stop(self) -> None:
        """Stop the server if it runs."""
        if self.proc is not None:
            stop_processes([self.proc], 10.0)


@pytest.fixture
def redis_server(tmp_path: Path) -> Iterator[RedisServer]:
    """Yield a running private redis-server with AOF (skips when the binary is missing)."""
    if not os.path.exists(REDIS_SERVER):
        pytest.skip("redis-server binary not found")
    server = RedisServer(tmp_path / "redis")
    server.start()
    yield server
    server.stop()


def client_for(server: RedisServer) -> redis.Redis:
    """Return a client that fails fast (the tests retry themselves, like the API's clients)."""
    return redis.Redis.from_url(server.url, socket_connect_timeout=1.0, socket_timeout=2.0)


class Workers:
    """Real worker processes (python -m workers.main) against one Redis and one data dir."""

    def __init__(self, data_dir: Path, url: str, log_dir: Path) -> None:
        self.data_dir, self.url, self.log_dir = data_dir, url, log_dir
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(self, name: str, **config: Any) -> subprocess.Popen[bytes]:
        """Start worker `name` with FAST timings plus `config`."""
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        env.pop("VEINMOSAIC_WORKER_CONFIG", None)
        cmd = [
            sys.executable, "-m", "workers.main", "--data-dir", str(self.data_dir), "--redis-url", self.url,
            "--prefix", PREFIX, "--consumer", f"fault-{name}", "--config-json", json.dumps({**FAST, **config}),
        ]  # fmt: skip
        proc = start_process(cmd, env, self.log_dir / f"worker-{name}.log", cwd=REPO)
        self.procs[name] = proc
        return proc

    def wait_started(self, timeout_s: float = 60.0) -> None:
        """Wait until every worker has connected and entered its loop (imports take seconds on a busy box)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(f"worker fault-{name} started" in self.log(name) for name in self.procs):
                return
            time.sleep(0.1)
        raise AssertionError(f"workers did not start within {timeout_s:.0f} s")

    def log(self, name: str) -> str:
        """Return worker `name`'s log so far."""
        return (self.log_dir / f"worker-{name}.log").read_text(errors="replace")

    def alive(self) -> dict[str, bool]:
        """Return which workers are still running."""
        return {name: p.poll() is None for name, p in self.procs.items()}

    def stop(self) -> None:
        """SIGTERM every worker, SIGKILL what does not stop within 15 s."""
        stop_processes(list(self.procs.values()), 15.0)


@pytest.fixture
def workers_factory(tmp_path: Path) -> Iterator[Callable[[Path, str], Workers]]:
    """Return a maker of Workers; all are stopped afterwards."""
    made: list[Workers] = []

    def make(data_dir: Path, url: str) -> Workers:
        w = Workers(data_dir, url, tmp_path)
        made.append(w)
        return w

    yield make
    for w in made:
        w.stop()


def start_serve(
    log_dir: Path, data_dir: Path, key: str, redis_url: str | None, **settings: str
) -> tuple[subprocess.Popen[bytes], int]:
    """Start `veinmosaic serve` (2 workers, FAST timings, PREFIX, `key` with every scope) on a free port, its
    output in log_dir/serve.log; without redis_url, REDIS_URL is unset (serve embeds a Redis). Return it, port."""
    port = free_port()
    keys = {key: ["ingest", "view", "admin"]}
    env = service_env(
        data_dir, keys, redis_url=redis_url, pythonpath=REPO, redis_prefix=PREFIX, worker_config=json.dumps(FAST),
        **settings,
    )  # fmt: skip
    if not redis_url:
        env.pop("REDIS_URL", None)
    env["PYTHONUNBUFFERED"] = "1"  # serve's lines ("serving on", restarts) reach serve.log at once
    return start_process(serve_command(port, 2), env, log_dir / "serve.log", cwd=REPO), port


def png(img: np.ndarray) -> bytes:
    """Return PNG bytes of an image."""
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


@dataclass
class Uploader:
    """Uploads as the API does (durable store, then enqueue), retrying refused attempts like a client."""

    store: SessionStore
    r: redis.Redis
    scan: Scan
    operations: int = 0  # upload attempts (each retry counts)
    refused: int = 0  # attempts that failed (storage or Redis fault): never answered 2xx
    accepted: set[int] = field(default_factory=set)

    def create(self) -> str:
        """Create the session and store all forces; return its id."""
        sid = self.store.create_session("f" * 64, "fault-test", self.scan.calibration).id
        self.store.put_forces(sid, np.column_stack([self.scan.force_t_s, self.scan.forces_n]))
        return sid

    def frame_bytes(self, seq: int) -> bytes:
        """Return the PNG bytes of frame seq."""
        return png(self.scan.frame(seq))

    def send(self, sid: str, seq: int, data: bytes | None = None, retry_for_s: float = 30.0) -> bool:
        """Store and enqueue one frame, retrying faults for up to retry_for_s; True once accepted."""
        data = self.frame_bytes(seq) if data is None else data
        deadline = time.monotonic() + retry_for_s
        while True:
            self.operations += 1
            try:
                self.store.put_frame(sid, seq, float(self.scan.frame_t_s[seq]), data, "png")
                queue.enqueue_frame(self.r, sid, seq, PREFIX)  # 2xx only after both, as the API does
                self.accepted.add(seq)
                return True
            except (OSError, redis.RedisError):
                self.refused += 1
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.2)

    def finish(self, sid: str, retry_for_s: float = 30.0) -> None:
        """Finish the session (store, then the finish marker), retrying faults."""
        deadline = time.monotonic() + retry_for_s
        while True:
            self.operations += 1
            try:
                self.store.finish(sid)
                queue.enqueue_finish(self.r, sid, PREFIX)
                return
            except (OSError, redis.RedisError):
                self.refused += 1
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)


def wait_done(store: SessionStore, sid: str, timeout_s: float, workers: Workers | None = None) -> None:
    """Wait until the session's status is done; fail (with the workers' state) after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError, ValueError):
            if store.get_meta(sid).status == "done":
                return
        time.sleep(0.1)
    alive = workers.alive() if workers else {}
    raise AssertionError(f"session not done after {timeout_s:.0f} s (workers alive: {alive})")


def delivery(
    data_dir: Path, r: redis.Redis, sid: str, accepted: set[int], poison: set[int] = frozenset()
) -> dict[str, int]:
    """Return {"lost", "duplicated", ...}: every accepted frame must have exactly one result row.

    lost: accepted frames with no row, declared missing, or rejected as a bad frame without being one.
    duplicated: repeated rows, Redis counting more frames than rows, or more first-writes of prepared frames
    (frames_prepared_total) than prepared files.
    """
    results = ResultsStore(data_dir)
    rows = results.read_path(sid, LIVE_VERSION) or []
    seqs = [int(row["seq"]) for row in rows]
    unique = set(seqs)
    by_seq = {int(row["seq"]): row for row in rows}
    bad = {s for s, row in by_seq.items() if row.get("reason") == "bad_frame"}
    missing = {s for s, row in by_seq.items() if row.get("reason") == "missing"}
    lost = len(accepted - unique) + len(missing & accepted) + len((bad - set(poison)) & accepted)
    counters = queue.session_counters(r, sid, PREFIX)
    prepared_files = len(list((results.version_dir(sid, LIVE_VERSION) / "prepared").glob("*.npz")))
    prepared_writes = int(r.hget(queue.metrics_key(PREFIX), "frames_prepared_total") or 0)
    duplicated = (len(seqs) - len(unique)) + max(0, counters["processed"] - len(unique))
    duplicated += max(0, prepared_writes - prepared_files)
    return {
        "accepted": len(accepted),
        "rows": len(seqs),
        "processed": counters["processed"],
        "lost": lost,
        "duplicated": duplicated,
        "poison": len(bad),
    }


def report(name: str, operations: int, faults: int, result: dict[str, int]) -> None:
    """Print the test's one-line report and assert nothing was lost or duplicated."""
    print(
        f"\nFAULT-REPORT {name}: operations={operations} faults={faults} accepted={result['accepted']} "
        f"processed={result['processed']} lost={result['lost']} duplicated={result['duplicated']}"
    )
    assert result["lost"] == 0, result
    assert result["duplicated"] == 0, result
    assert result["rows"] == result["accepted"], result
    assert result["processed"] == result["accepted"], result
