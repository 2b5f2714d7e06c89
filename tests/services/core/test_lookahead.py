"""Work done ahead on threads and handed back in order (services/core/lookahead.py)."""

from __future__ import annotations

import threading

from services.core.lookahead import in_order_ahead


def test_results_come_in_order_each_built_once_and_never_more_than_ahead() -> None:
    started: list[int] = []
    lock = threading.Lock()

    def build(item: int) -> int:
        with lock:
            started.append(item)
        return item * item

    seen = []
    for k, value in enumerate(in_order_ahead(build, list(range(20)), ahead=3)):
        with lock:
            # when item k is handed back, at most items k .. k + 3 have been started (the next one is queued first)
            assert max(started) <= k + 3
        seen.append(value)
    assert seen == [i * i for i in range(20)]
    assert sorted(started) == list(range(20))


def test_an_empty_sequence_yields_nothing() -> None:
    assert list(in_order_ahead(lambda item: item, [], ahead=4)) == []
