"""Each worker's held-session count in Redis (services/jobs/worker_load.py): what a kick's taker compares."""

from __future__ import annotations

from services.jobs import worker_load
from tests.workers.conftest import Backend


def test_fewest_held_elsewhere_ignores_this_worker_and_expired_ones(backend: Backend) -> None:
    r, prefix = backend.r, backend.prefix
    assert worker_load.fewest_held_elsewhere(r, prefix, "w1") is None  # alone: nobody to leave a session to
    worker_load.publish_held(r, prefix, "w1", 3)
    assert worker_load.fewest_held_elsewhere(r, prefix, "w1") is None  # its own count does not count
    worker_load.publish_held(r, prefix, "w2", 2)
    worker_load.publish_held(r, prefix, "w3", 1)
    assert worker_load.fewest_held_elsewhere(r, prefix, "w1") == 1
    assert worker_load.fewest_held_elsewhere(r, prefix, "w3") == 2
    worker_load.publish_held(r, prefix, "w3", 4)  # a newer count replaces the old one
    assert worker_load.fewest_held_elsewhere(r, prefix, "w1") == 2
    # a worker that stops publishing (dead, or in a long job) drops out when its count expires: its field is
    # removed by the next reader; here w2's expiry is moved into the past by the server's clock
    fields = r.hgetall(worker_load.load_key(prefix))
    assert {k.decode() if isinstance(k, bytes) else k for k in fields} == {"w1", "w2", "w3"}
    r.hset(worker_load.load_key(prefix), "w2", "2:1")
    assert worker_load.fewest_held_elsewhere(r, prefix, "w1") == 4
    assert not r.hexists(worker_load.load_key(prefix), "w2")
    assert r.hexists(worker_load.load_key(prefix), "w1")
    assert worker_load.fewest_held_elsewhere(r, prefix + "other:", "w1") is None  # deployments apart


def test_a_count_expires_after_the_ttl_by_the_servers_clock(backend: Backend) -> None:
    r, prefix = backend.r, backend.prefix
    worker_load.publish_held(r, prefix, "w2", 1)
    value = r.hget(worker_load.load_key(prefix), "w2")
    count, expiry_ms = (value.decode() if isinstance(value, bytes) else value).split(":")
    seconds, micros = r.time()
    now_ms = seconds * 1000 + micros // 1000
    assert count == "1"
    # the expiry is LOAD_TTL_MS after the server's now (tolerance 1 s: the two calls' round trips)
    assert worker_load.LOAD_TTL_MS - 1000 <= int(expiry_ms) - now_ms <= worker_load.LOAD_TTL_MS
