"""A real API process for tests: uvicorn in a subprocess on a free port, its stderr (the JSON logs) in a file.

Redis is the server at REDIS_URL (with a private key prefix, cleaned afterwards) when set, else the embedded
one the app starts in its data directory.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import redis

READY_TIMEOUT_S = 30.0


def free_port() -> int:
    """Return a free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class LiveAPI:
    """A running API process: its URL, process, data directory and log file."""

    base_url: str
    proc: subprocess.Popen[bytes]
    data_dir: Path
    log_path: Path

    def log_lines(self) -> list[str]:
        """Return every line the process wrote to stderr/stdout so far."""
        return self.log_path.read_text(errors="replace").splitlines()


@contextmanager
def live_api(tmp_path: Path, keys: dict[str, list[str]], **settings: str) -> Iterator[LiveAPI]:
    """Start the API (settings as VEINMOSAIC_<NAME> variables) and stop it afterwards."""
    port = free_port()
    data_dir = tmp_path / f"data-{port}"
    prefix = f"vmtest:{uuid.uuid4().hex}:"
    env = {k: v for k, v in os.environ.items() if not k.startswith("VEINMOSAIC_")}
    env.update(
        {
            "VEINMOSAIC_DATA_DIR": str(data_dir),
            "VEINMOSAIC_API_KEYS": json.dumps(keys),
            "VEINMOSAIC_REDIS_PREFIX": prefix,
            "VEINMOSAIC_TOKEN_SECRET": uuid.uuid4().hex,
            **{f"VEINMOSAIC_{k.upper()}": v for k, v in settings.items()},
        }
    )
    log_path = tmp_path / f"api-{port}.log"
    command = [
        sys.executable, "-m", "uvicorn", "api.app:create_app", "--factory",
        "--host", "127.0.0.1", "--port", str(port), "--no-access-log", "--log-level", "info",
    ]  # fmt: skip
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
    api = LiveAPI(f"http://127.0.0.1:{port}", proc, data_dir, log_path)
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while True:
            try:
                if httpx.get(f"{api.base_url}/healthz", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the API did not start:\n" + "\n".join(api.log_lines()[-20:]))
            time.sleep(0.1)
        yield api
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if os.environ.get("REDIS_URL"):
            r = redis.Redis.from_url(os.environ["REDIS_URL"])
            keys_found = list(r.scan_iter(match=f"{prefix}*"))
            if keys_found:
                r.delete(*keys_found)
            r.close()
