"""Per-key quotas of sessions and frames (services.jobs.quotas): counted per owner and fixed window in Redis."""

from __future__ import annotations

import threading

import pytest
import redis

from services.jobs import queue, quotas
from tests.services.jobs.test_queue import rq

__all__ = ["rq"]


def test_take_counts_up_to_the_limit_per_owner_and_window(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    now = 7200.0 + 100.0  # 100 s into a window of 3600 s
    for used in (1, 2):
        key = quotas.take(r, prefix, "a" * 64, "frames", 2, 3600, now=now)
        assert key == queue.owner_quota_key("a" * 64, "frames", 2, prefix) and int(r.get(key)) == used
    with pytest.raises(quotas.KeyQuotaError) as refused:
        quotas.take(r, prefix, "a" * 64, "frames", 2, 3600, now=now)
    assert refused.value.retry_after_s == 3500 and "2 frames per 3600 s" in str(refused.value)
    assert int(r.get(queue.owner_quota_key("a" * 64, "frames", 2, prefix))) == 2  # the refusal counted nothing
    assert 3600 < r.ttl(queue.owner_quota_key("a" * 64, "frames", 2, prefix)) <= 7200  # the counter expires
    assert quotas.take(r, prefix, "b" * 64, "frames", 2, 3600, now=now)  # another owner
    assert quotas.take(r, prefix, "a" * 64, "sessions", 2, 3600, now=now)  # another quota
    assert quotas.take(r, prefix, "a" * 64, "frames", 2, 3600, now=now + 3600)  # the next window
    with pytest.raises(quotas.KeyQuotaError):
        quotas.take(r, prefix, "a" * 64, "frames", 3, 3600, n=2, now=now)  # 2 + 2 > 3: all or nothing
    assert quotas.take(r, prefix, "a" * 64, "frames", 0, 3600, now=now) is None  # 0: no limit, nothing counted


def test_give_back_returns_units_never_below_zero(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    key = quotas.take(r, prefix, "a" * 64, "sessions", 1, 60, now=30.0)
    with pytest.raises(quotas.KeyQuotaError):
        quotas.take(r, prefix, "a" * 64, "sessions", 1, 60, now=30.0)
    quotas.give_back(r, key)
    quotas.give_back(r, key)  # twice: the counter stays at 0
    assert int(r.get(key)) == 0
    quotas.give_back(r, None)  # nothing was counted (no limit)
    assert quotas.take(r, prefix, "a" * 64, "sessions", 1, 60, now=30.0) == key


def test_concurrent_takes_never_pass_the_limit(rq: tuple[redis.Redis, str]) -> None:
    r, prefix = rq
    passed: list[bool] = []

    def one() -> None:
        try:
            quotas.take(r, prefix, "c" * 64, "frames", 25, 3600)
            passed.append(True)
        except quotas.KeyQuotaError:
            passed.append(False)

    threads = [threading.Thread(target=one) for _ in range(60)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert passed.count(True) == 25
