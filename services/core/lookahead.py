"""Work done a few items ahead on threads and handed back in order (OpenCV and decoding free the GIL)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def in_order_ahead(build: Callable[[T], R], items: Sequence[T], ahead: int, threads: int = 2) -> Iterator[R]:
    """Yield build(item) for each item in order, computed up to `ahead` items ahead on `threads` threads."""
    with ThreadPoolExecutor(max_workers=threads) as pool:
        futures: list[Future[R] | None] = [pool.submit(build, item) for item in items[:ahead]]
        for k in range(len(items)):
            if k + ahead < len(items):
                futures.append(pool.submit(build, items[k + ahead]))
            future = futures[k]
            assert future is not None
            yield future.result()
            futures[k] = None  # the result is the caller's now: hold no reference to it
