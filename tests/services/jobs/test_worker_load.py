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
    # a worker that stops publishing (dead, or in a long job) drops out when its count expires
    ttl = r.pttl(f"{prefix}load:w2")
    assert 0 < ttl <= worker_load.LOAD_TTL_MS
    r.delete(f"{prefix}load:w2")
    assert worker_load.fewest_held_elsewhere(r, prefix, "w1") == 4
    assert worker_load.fewest_held_elsewhere(r, prefix + "other:", "w1") is None  # deployments apart
