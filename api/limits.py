"""Per-client rate limits (token buckets) and the cap on open event streams, both per API process.

Two kinds of request are rate-limited, each in its own table of buckets (`Settings.rate_limit_*`):

- "anonymous": requests refused for want of a valid credential (no key, an unknown key, a bad or expired
  viewer token), per client address. A client over the limit is answered 429 before any disk work; a caller
  with a valid credential from the same address is never throttled by this table.
- "expensive": the reads that render a document per call (export.dcm?layer=report, sheet.pdf/png, GET
  /report), per client address and caller.

A refused request answers 429 with Retry-After (api.errors.TooManyRequests): the seconds until the bucket
holds a token again. Buckets live in memory (no Redis round trip per refused request, and they keep working
when Redis is down); with several API processes (`api_workers`) each holds its own, so a client may get up to
that many times the rate. The tables are bounded: the least recently used bucket is dropped when one is full.

StreamSlots counts the open event streams: at most `events_max_per_principal` per caller (429 beyond) and
`events_max_total` in all (503 beyond).
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING

from fastapi import Request

from api.errors import ServiceUnavailable, TooManyRequests

if TYPE_CHECKING:  # api.auth imports this module
    from api.auth import Principal

MAX_BUCKETS = 20_000


class TokenBuckets:
    """Token buckets by key: `burst` tokens, refilled at `per_s` a second; thread-safe, bounded in size."""

    def __init__(self, per_s: float, burst: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.per_s = float(per_s)
        self.burst = int(burst)
        self.clock = clock
        self._lock = threading.Lock()
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # key -> (tokens, at)

    def take(self, key: str) -> float | None:
        """Return None when `key` may go on (one token taken), else the seconds until it may (nothing taken)."""
        if self.burst <= 0:
            return None  # a burst of 0: no limit
        now = self.clock()
        with self._lock:
            tokens, at = self._buckets.pop(key, (float(self.burst), now))
            tokens = min(float(self.burst), tokens + (now - at) * self.per_s)
            if tokens >= 1.0:
                self._buckets[key] = (tokens - 1.0, now)
                wait = None
            else:
                self._buckets[key] = (tokens, now)
                wait = (1.0 - tokens) / self.per_s
            while len(self._buckets) > MAX_BUCKETS:
                self._buckets.popitem(last=False)
        return wait


def client_address(request: Request) -> str:
    """Return the client's address as the ASGI server reports it ("unknown" without one)."""
    client = request.client
    return client.host if client is not None else "unknown"


def principal_key(principal: Principal) -> str:
    """Return who a principal is for the limits: "token:<session>" for a viewer link, else "key:<fingerprint>"."""
    if principal.session_id is not None:
        return f"token:{principal.session_id}"
    return f"key:{principal.fingerprint or ''}"


def _buckets(request: Request, name: str) -> TokenBuckets:
    """Return the app's bucket table `name` ("anonymous" or "expensive"), made from the settings on first use."""
    state = request.app.state
    tables: dict[str, TokenBuckets] | None = getattr(state, "rate_limits", None)
    if tables is None:
        tables = state.rate_limits = {}
    table = tables.get(name)
    if table is None:
        s = state.settings
        per_s, burst = getattr(s, f"rate_limit_{name}_per_s"), getattr(s, f"rate_limit_{name}_burst")
        table = tables[name] = TokenBuckets(per_s, burst)
    return table


def too_many(wait_s: float, what: str) -> TooManyRequests:
    """Return the 429 of a request over a rate limit, with Retry-After rounded up to whole seconds."""
    return TooManyRequests(f"too many {what} from this client; retry later", max(1, math.ceil(wait_s)))


def refuse_unauthenticated(request: Request, refusal: Exception) -> Exception:
    """Return what to raise for a request without a valid credential: `refusal` (401), or 429 over the limit."""
    wait = _buckets(request, "anonymous").take(client_address(request))
    return refusal if wait is None else too_many(wait, "requests without a valid credential")


def check_expensive(request: Request, principal: Principal) -> None:
    """Return None when the caller may run one more expensive read; TooManyRequests (429) when over its limit."""
    wait = _buckets(request, "expensive").take(f"{client_address(request)}|{principal_key(principal)}")
    if wait is not None:
        raise too_many(wait, "report and export requests")


class StreamSlots:
    """The open event streams of one API process, by caller; used from the event loop only."""

    def __init__(self) -> None:
        self.open: dict[str, int] = {}

    @property
    def total(self) -> int:
        """Return how many streams are open."""
        return sum(self.open.values())

    def acquire(self, who: str, per_principal: int, total: int, retry_after_s: int) -> Callable[[], None]:
        """Return the release function of a slot taken for `who`; 429 over its cap, 503 over the total cap."""
        if self.open.get(who, 0) >= per_principal:
            raise TooManyRequests(
                f"at most {per_principal} open event streams per caller; close one or retry later", retry_after_s
            )
        if self.total >= total:
            raise ServiceUnavailable("too many open event streams; retry later", retry_after_s, code="too_many_streams")
        self.open[who] = self.open.get(who, 0) + 1
        released = False

        def release() -> None:
            nonlocal released
            if released:
                return
            released = True
            left = self.open.get(who, 0) - 1
            if left > 0:
                self.open[who] = left
            else:
                self.open.pop(who, None)

        return release
