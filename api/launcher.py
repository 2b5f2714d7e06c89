"""`veinmosaic serve`: one launcher that owns the embedded Redis (when REDIS_URL is unset), the API server
process and N worker processes, and stops them all together."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import redis

from services.redis_backend import close, connect, read_embedded_url

READY_TIMEOUT_S = 60.0


@dataclass
class Service:
    """The running service: API on host:port, `workers` worker processes, one Redis, one data dir."""

    data_dir: Path
    host: str = "127.0.0.1"
    port: int = 8000
    workers: int = 2
    redis_url: str | None = None
    extra_env: dict[str, str] = field(default_factory=dict)
    processes: list[subprocess.Popen[bytes]] = field(default_factory=list)
    embedded: redis.Redis | None = None

    @property
    def base_url(self) -> str:
        """Return the API's base URL."""
        return f"http://{self.host}:{self.port}"

    def _env(self, redis_url: str) -> dict[str, str]:
        env = dict(os.environ)
        env.update(self.extra_env)
        env["REDIS_URL"] = redis_url
        env["VEINMOSAIC_DATA_DIR"] = str(self.data_dir)
        return env

    def start(self) -> None:
        """Start Redis (embedded when no URL), the workers and the API; return once /readyz answers 200."""
        try:
            self._start()
        except BaseException:
            self.stop()
            raise

    def _start(self) -> None:
        self.data_dir = Path(self.data_dir).resolve()
        self.data_dir.mkdir(parents=True, exist_ok=True)
        url = self.redis_url
        if not url:
            self.embedded = connect(None, self.data_dir)
            url = read_embedded_url(self.data_dir)
            assert url, "embedded Redis did not publish its URL"
        env = self._env(url)
        for _ in range(self.workers):
            self.processes.append(subprocess.Popen([sys.executable, "-m", "workers.main"], env=env))
        api = [
            sys.executable, "-m", "uvicorn", "api.app:create_app", "--factory",
            "--host", self.host, "--port", str(self.port), "--no-access-log", "--log-level", "warning",
        ]  # fmt: skip
        self.processes.append(subprocess.Popen(api, env=env))
        self.wait_ready()

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Block until GET /readyz is 200; raise RuntimeError if a process died or time ran out."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            dead = [p for p in self.processes if p.poll() is not None]
            if dead:
                raise RuntimeError(f"a service process exited early (code {dead[0].returncode})")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{self.base_url}/readyz", timeout=2.0).status_code == 200:
                    return
            time.sleep(0.2)
        raise RuntimeError(f"the API did not become ready within {timeout_s:.0f} s")

    def stop(self) -> None:
        """Stop the API and workers (SIGTERM, then SIGKILL after 10 s), then the embedded Redis."""
        for p in self.processes:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 10.0
        for p in self.processes:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.processes.clear()
        if self.embedded is not None:
            close(self.embedded)
            self.embedded = None

    def wait(self) -> int:
        """Block until any process exits or SIGINT/SIGTERM arrives; return the exit code to use."""
        stop = {"flag": False}

        def handler(_signum: int, _frame: object) -> None:
            stop["flag"] = True

        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, handler)
        while not stop["flag"]:
            if any(p.poll() is not None for p in self.processes):
                return 1
            time.sleep(0.5)
        return 0

    def __enter__(self) -> Service:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
