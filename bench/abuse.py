"""Abuse scenarios against a bare API process on loopback: what the audit log, Redis and readiness do.

    python bench/abuse.py [--requests 3000] [--threads 20] [--streams 200] [--quota 50]

Starts the API alone (uvicorn, no workers; Redis: REDIS_URL with a private key prefix, deleted at the end, or
the embedded one) with its default limits, then runs two floods while a probe times GET /readyz every 100 ms:

- anonymous flood: `--requests` unauthenticated GETs of random session ids from `--threads` threads (issue 34:
  the audit log grew 1.19 MB for 3000 before per-client coalescing and the 429s);
- stream flood: `--streams` event streams opened at once with one viewer token and held open 3 s;
- one key over its quota: with `queue_max_jobs_per_key` = `--quota`, one key asks for twice that many PACS sends
  (no worker runs them: they stay queued), then another key asks for one (it must get its 202).

Prints one table: answers by status, audit log growth, Redis clients and memory before and at the peak, and
/readyz latency (p50, max) during each flood.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import redis

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cli.launcher import api_command, free_port, service_env, start_process, stop_processes, wait_until_ready  # noqa: E402
from services.jobs.redis_backend import read_embedded_url  # noqa: E402

KEY = "abuse-bench-key-0123456789abcdef"
OTHER_KEY = "abuse-bench-other-key-0123456789abcdef"
CALIBRATION = {
    "image_size": [64, 48],
    "camera_matrix": [[80.0, 0.0, 31.5], [0.0, 80.0, 23.5], [0.0, 0.0, 1.0]],
    "px_per_mm": 8.0,
}


@dataclass
class Outcome:
    """What one flood did: answers by status, audit growth (bytes), Redis before/peak, /readyz latencies (s)."""

    name: str
    answers: Counter[int] = field(default_factory=Counter)
    wall_s: float = 0.0
    audit_bytes: int = 0
    redis_clients: tuple[int, int] = (0, 0)
    redis_memory: tuple[int, int] = (0, 0)
    readyz: list[float] = field(default_factory=list)
    readyz_failures: int = 0

    def row(self) -> str:
        """Return the Markdown table row."""
        answers = ", ".join(f"{s} x{n}" for s, n in sorted(self.answers.items()))
        lat = [1000 * s for s in self.readyz] or [0.0]
        return (
            f"| {self.name} | {sum(self.answers.values())} in {self.wall_s:.1f} s | {answers} | "
            f"{self.audit_bytes / 1024:.1f} KB | {self.redis_clients[0]} -> {self.redis_clients[1]} | "
            f"{self.redis_memory[0] / 2**20:.1f} -> {self.redis_memory[1] / 2**20:.1f} MB | "
            f"{statistics.median(lat):.0f} / {max(lat):.0f} ms | {self.readyz_failures} |"
        )


class Probe:
    """A thread timing GET /readyz every 100 ms and sampling Redis (clients, memory) until stopped."""

    def __init__(self, base: str, r: redis.Redis, outcome: Outcome) -> None:
        self.base, self.r, self.outcome = base, r, outcome
        info = r.info()
        outcome.redis_clients = (int(info["connected_clients"]), int(info["connected_clients"]))
        outcome.redis_memory = (int(info["used_memory"]), int(info["used_memory"]))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        with httpx.Client(base_url=self.base, timeout=10) as http:
            while not self._stop.is_set():
                t0 = time.perf_counter()
                try:
                    ok = http.get("/readyz").status_code == 200
                except httpx.HTTPError:
                    ok = False
                self.outcome.readyz.append(time.perf_counter() - t0)
                self.outcome.readyz_failures += 0 if ok else 1
                info = self.r.info()
                c0, c1 = self.outcome.redis_clients
                m0, m1 = self.outcome.redis_memory
                self.outcome.redis_clients = (c0, max(c1, int(info["connected_clients"])))
                self.outcome.redis_memory = (m0, max(m1, int(info["used_memory"])))
                self._stop.wait(0.1)

    def __enter__(self) -> Probe:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def audit_size(data_dir: Path) -> int:
    """Return the audit log's size in bytes (0 before its first record)."""
    path = data_dir / "audit" / "audit.jsonl"
    return path.stat().st_size if path.exists() else 0


def anonymous_flood(base: str, data_dir: Path, r: redis.Redis, n: int, threads: int) -> Outcome:
    """Return what n unauthenticated GETs of random session ids from `threads` threads did."""
    outcome = Outcome(f"anonymous flood ({threads} threads)")
    local = threading.local()

    def one(_: int) -> int:
        if not hasattr(local, "http"):
            local.http = httpx.Client(base_url=base, timeout=10)
        try:
            return local.http.get(f"/v1/sessions/{uuid.uuid4().hex}").status_code
        except httpx.HTTPError:
            return 0

    before = audit_size(data_dir)
    with Probe(base, r, outcome):
        t0 = time.perf_counter()
        with ThreadPoolExecutor(threads) as pool:
            outcome.answers.update(pool.map(one, range(n)))
        outcome.wall_s = time.perf_counter() - t0
    outcome.audit_bytes = audit_size(data_dir) - before
    return outcome


async def _streams(base: str, url: str, n: int, hold_s: float, answers: Counter[int]) -> None:
    limits = httpx.Limits(max_connections=n + 10, max_keepalive_connections=0)
    async with httpx.AsyncClient(base_url=base, timeout=30, limits=limits) as http:

        async def one() -> None:
            try:
                async with http.stream("GET", url) as resp:
                    answers[resp.status_code] += 1
                    if resp.status_code == 200:
                        await asyncio.sleep(hold_s)
            except httpx.HTTPError:
                answers[0] += 1

        await asyncio.gather(*(one() for _ in range(n)))


def stream_flood(base: str, data_dir: Path, r: redis.Redis, n: int) -> Outcome:
    """Return what n event streams opened at once with one viewer token (held 3 s) did."""
    outcome = Outcome("stream flood (one token)")
    created = httpx.post(
        f"{base}/v1/sessions", json={"calibration": CALIBRATION}, headers={"Authorization": f"Bearer {KEY}"}
    ).json()
    url = f"/v1/sessions/{created['id']}/events?token={created['viewer_token']}"
    before = audit_size(data_dir)
    with Probe(base, r, outcome):
        t0 = time.perf_counter()
        asyncio.run(_streams(base, url, n, 3.0, outcome.answers))
        outcome.wall_s = time.perf_counter() - t0
    outcome.audit_bytes = audit_size(data_dir) - before
    return outcome


def quota_flood(base: str, data_dir: Path, r: redis.Redis, quota: int) -> Outcome:
    """Return what 2 x quota send requests of one key did, with the other key's one request last ("other: ...")."""
    outcome = Outcome(f"one key over its quota ({quota} jobs)")
    before = audit_size(data_dir)
    with Probe(base, r, outcome), httpx.Client(base_url=base, timeout=10) as http:
        t0 = time.perf_counter()
        for key in (KEY, OTHER_KEY):
            auth = {"Authorization": f"Bearer {key}"}
            sid = http.post("/v1/sessions", json={"calibration": CALIBRATION}, headers=auth).json()["id"]
            for _ in range(2 * quota if key == KEY else 1):
                status = http.post(f"/v1/sessions/{sid}/send", json={"destination": "bench"}, headers=auth).status_code
                outcome.answers[status if key == KEY else 1000 + status] += 1  # the other key's: 1202, 1429, ...
        outcome.wall_s = time.perf_counter() - t0
    outcome.audit_bytes = audit_size(data_dir) - before
    return outcome


def main(argv: list[str] | None = None) -> int:
    """Start the API, run both floods, print the table."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--requests", type=int, default=3000)
    p.add_argument("--threads", type=int, default=20)
    p.add_argument("--streams", type=int, default=200)
    p.add_argument("--quota", type=int, default=50)
    args = p.parse_args(argv)
    redis_url = os.environ.get("REDIS_URL")
    tmp = Path(tempfile.mkdtemp(prefix="vm-abuse-"))
    data_dir = tmp / "data"
    prefix = f"vmabuse:{uuid.uuid4().hex[:8]}:"
    keys = {KEY: ["ingest", "view", "admin"], OTHER_KEY: ["ingest"]}
    pacs = '{"bench": {"dicomweb": "http://127.0.0.1:9/dicom-web"}}'  # never contacted: no worker runs
    env = service_env(data_dir, keys, redis_url=redis_url, pythonpath=ROOT, log_level="WARNING", redis_prefix=prefix,
                      pacs_destinations=pacs, queue_max_jobs_per_key=str(args.quota))  # fmt: skip
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    api = start_process(api_command("127.0.0.1", port), env, cwd=ROOT)
    r: redis.Redis | None = None
    try:
        wait_until_ready(f"{base}/readyz", 90, [api])
        r = redis.Redis.from_url(redis_url or read_embedded_url(data_dir) or "")
        results = [
            anonymous_flood(base, data_dir, r, args.requests, args.threads),
            stream_flood(base, data_dir, r, args.streams),
            quota_flood(base, data_dir, r, args.quota),
        ]
    finally:
        stop_processes([api])
        if r is not None and redis_url:
            keys = list(r.scan_iter(match=f"{prefix}*", count=1000))
            if keys:
                r.delete(*keys)
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\n{os.cpu_count()} CPUs; the API alone (1 uvicorn process), default limits; Redis: "
          f"{'REDIS_URL' if redis_url else 'embedded'}\n")  # fmt: skip
    print("| scenario | requests | answers | audit log growth | Redis clients (before -> peak) | Redis memory | "
          "/readyz p50 / max | /readyz failures |")  # fmt: skip
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for outcome in results:
        print(outcome.row())
    print("\n(answers 1xxx: the other key's request, status xxx)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
