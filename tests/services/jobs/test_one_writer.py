"""One writer: every Redis record (streams, job records, counters, sets, lists) is written by services.jobs.

The api and the workers decide what to write; only services/jobs calls Redis's write commands, each record
through one function (jobs: services.jobs.reprocess; dead letters: services.jobs.dead_letters; counters:
queue.incr_metric; events: queue.add_event). A raw write anywhere else fails this test with its place.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
WRITES = frozenset(
    {
        "xadd", "hset", "hsetnx", "hmset", "hincrby", "hincrbyfloat", "incr", "incrby", "incrbyfloat", "decr",
        "rpush", "lpush", "sadd", "zadd", "setex",
    }
)  # fmt: skip
ONE_WRITER = REPO / "services" / "jobs"


def _raw_writes(path: Path) -> list[str]:
    """Return "file:line .name(" of every call of a Redis write command in a Python file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return [
        f"{path.relative_to(REPO)}:{node.lineno} .{node.func.attr}("
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in WRITES
    ]


def _sources() -> list[Path]:
    return sorted(p for top in ("api", "workers", "services") for p in (REPO / top).rglob("*.py"))


def test_no_raw_redis_write_outside_services_jobs() -> None:
    outside = [w for p in _sources() if ONE_WRITER not in p.parents for w in _raw_writes(p)]
    assert outside == [], "write Redis records through services.jobs:\n" + "\n".join(outside)


def test_each_record_has_its_one_writer() -> None:
    inside = {p.name: [w.split(" ")[1] for w in _raw_writes(p)] for p in ONE_WRITER.glob("*.py")}
    assert ".xadd(" in inside["queue.py"] and ".hincrby(" in inside["queue.py"]  # the scan sees real calls
    assert inside["dead_letters.py"] == [".xadd(", ".hincrby("]  # the dead-letter stream, failure counts
    # the job records: written (created, re-queued, updated) by services.jobs.reprocess alone
    job_writers = [
        p.name for p in ONE_WRITER.glob("*.py") if "job_key(" in p.read_text() and ".hset(" in inside[p.name]
    ]
    assert job_writers == ["reprocess.py"]
