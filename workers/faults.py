"""Infrastructure faults (storage full or failing, Redis unreachable or loading) versus a job's own bad content.

A transient fault is never held against a job: the job is retried after a bounded exponential back-off and is
never dead-lettered or marked rejected for it. Only a job's own content (an undecodable frame, a wrong size,
a bug it triggers every time) counts towards max_deliveries.
"""

from __future__ import annotations

import errno
import random

import redis

from services.log_format import describe, failure_frames, failure_reason

__all__ = ["describe", "failure_frames", "failure_reason"]  # re-exported: the workers' fault vocabulary


TRANSIENT_ERRNOS: frozenset[int] = frozenset(
    code
    for code in (
        errno.ENOSPC,  # disk full
        getattr(errno, "EDQUOT", errno.ENOSPC),  # quota exceeded
        errno.EIO,  # failing device / network storage
        errno.EROFS,  # volume remounted read-only after an error
        errno.ENOMEM,
        errno.EMFILE,
        errno.ENFILE,
        errno.EAGAIN,
        errno.EBUSY,
        errno.EINTR,
        errno.ETIMEDOUT,
        errno.EACCES,  # permissions of the volume: an operator's fix, never the frame's fault
        errno.EPERM,
        getattr(errno, "ESTALE", errno.EIO),  # NFS
        getattr(errno, "ENOLCK", errno.EIO),
        getattr(errno, "ENOTCONN", errno.EIO),
    )
)
# Replies of a Redis server that is up but cannot serve writes right now.
_REDIS_TRANSIENT_REPLIES = ("MISCONF", "LOADING", "OOM", "READONLY", "MASTERDOWN", "TRYAGAIN", "BUSY", "NOREPLICAS")


def is_transient(exc: BaseException) -> bool:
    """Return True if `exc` (or an exception it was raised from) is an infrastructure fault worth waiting out."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, redis.ConnectionError | redis.TimeoutError | redis.ReadOnlyError):
            return True  # BusyLoadingError is a ConnectionError
        if isinstance(cur, redis.ResponseError) and str(cur).upper().startswith(_REDIS_TRANSIENT_REPLIES):
            return True
        if isinstance(cur, ConnectionError | TimeoutError):  # socket-level, outside redis-py's wrappers
            return True
        if isinstance(cur, OSError) and cur.errno in TRANSIENT_ERRNOS:
            return True
        cur = cur.__cause__ or cur.__context__
    return False


class Backoff:
    """Bounded exponential back-off with jitter: first_s, 2 first_s, ... up to max_s; reset() after a success."""

    def __init__(self, first_s: float = 0.1, max_s: float = 5.0) -> None:
        self.first_s = first_s
        self.max_s = max_s
        self.failures = 0

    def next(self) -> float:
        """Return the delay (s) before the next attempt and count one more failure."""
        delay = min(self.max_s, self.first_s * (2.0 ** min(self.failures, 30)))
        self.failures += 1
        return delay * random.uniform(0.8, 1.0)

    def peek(self) -> float:
        """Return the delay (s) next() would return (without jitter), without counting a failure."""
        return min(self.max_s, self.first_s * (2.0 ** min(self.failures, 30)))

    def reset(self) -> None:
        """Forget past failures."""
        self.failures = 0
