"""A real API process for tests: uvicorn in a subprocess on a free port, its stderr (the JSON logs) in a file.

Redis is the server at REDIS_URL (with a private key prefix, cleaned afterwards) when set, else the embedded
one the app starts in its data directory.
"""

from __future__ import annotations

import os
import subprocess
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import redis

from cli.launcher import api_command, free_port, service_env, start_process, stop_processes, wait_until_ready

__all__ = ["LiveAPI", "free_port", "live_api"]

READY_TIMEOUT_S = 30.0


@dataclass
class LiveAPI:
    """A running API process: its URL, process, data directory, log file and Redis key prefix."""

    base_url: str
    proc: subprocess.Popen[bytes]
    data_dir: Path
    log_path: Path
    prefix: str = "vm:"

    def log_lines(self) -> list[str]:
        """Return every line the process wrote to stderr/stdout so far."""
        return self.log_path.read_text(errors="replace").splitlines()


@contextmanager
def live_api(tmp_path: Path, keys: dict[str, list[str]], **settings: str) -> Iterator[LiveAPI]:
    """Start the API (settings as VEINMOSAIC_<NAME> variables) and stop it afterwards."""
    port = free_port()
    data_dir = tmp_path / f"data-{port}"
    prefix = f"vmtest:{uuid.uuid4().hex}:"
    env = service_env(data_dir, keys, clean=True, redis_prefix=prefix, token_secret=uuid.uuid4().hex, **settings)
    log_path = tmp_path / f"api-{port}.log"
    proc = start_process(api_command("127.0.0.1", port, log_level="info"), env, log_path)
    api = LiveAPI(f"http://127.0.0.1:{port}", proc, data_dir, log_path, prefix)
    try:
        try:
            wait_until_ready(f"{api.base_url}/healthz", READY_TIMEOUT_S, [proc])
        except RuntimeError as exc:
            raise RuntimeError(f"the API did not start ({exc}):\n" + "\n".join(api.log_lines()[-20:])) from None
        yield api
    finally:
        stop_processes([proc], 15.0)
        if os.environ.get("REDIS_URL"):
            r = redis.Redis.from_url(os.environ["REDIS_URL"])
            keys_found = list(r.scan_iter(match=f"{prefix}*"))
            if keys_found:
                r.delete(*keys_found)
            r.close()
