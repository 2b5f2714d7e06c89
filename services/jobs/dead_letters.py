"""The dead-letter stream <prefix>dead and the failure counts that lead to it: the one writer of both.

An entry that failed max_deliveries times (a frame job, a reprocess or send job) and a frame whose registration
failed as often are appended to the dead-letter stream with what failed and why, and counted in the metric
dead_letters_total. Registration failures are counted per frame in <prefix>regfail:<id>:<v>.
"""

from __future__ import annotations

from collections.abc import Mapping

import redis

from services.jobs import queue


def dead_letter(r: redis.Redis, fields: Mapping[str, str], prefix: str = queue.DEFAULT_PREFIX) -> None:
    """Append `fields` to the dead-letter stream and count it in dead_letters_total (one round trip)."""
    pipe = r.pipeline(transaction=False)
    pipe.xadd(queue.dead_stream(prefix), dict(fields))
    queue.incr_metric(pipe, "dead_letters_total", prefix=prefix)
    pipe.execute()


def count_registration_failure(
    r: redis.Redis, session_id: str, version: int, seq: int, prefix: str = queue.DEFAULT_PREFIX
) -> int:
    """Return the registration failures so far of frame `seq` of (session, version), counting one more now."""
    return int(r.hincrby(queue.regfail_key(session_id, version, prefix), str(int(seq)), 1))
