"""Bounded load test on loopback: frame uploaders at a fixed arrival rate and Deep Zoom tile viewers together,
against a real `veinmosaic serve` (API + workers, own redis-server with AOF), while the scans process.

    python bench/load.py --upload-rate 200 --viewers 32 --tile-rate 5 --seconds 10

Open loop: upload i is started at t0 + i / rate whether or not earlier ones finished (a slow server shows
as latency, not as a lower offered rate). 640x480 PNG frames of the simulated short scan, spread over
--sessions sessions (default: one per 10 frames/s, a probe's rate); each viewer reads mosaic.json of a
finished session, then fetches its tiles at --tile-rate per second. The client sends pre-built requests over
keep-alive connections (bench/raw_http.py), so it needs a few % of a core, not the server's share. Stops by
itself after --seconds and prints one table (throughput, p50/p99, errors).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.raw_http import RawHttp, multipart  # noqa: E402
from cli.launcher import (  # noqa: E402
    free_port,
    serve_command,
    service_env,
    start_process,
    stop_processes,
    wait_until_ready,
)
from services.core.simulation.scenarios import simulate  # noqa: E402

KEY = "load-test-key-0123456789abcdef"


@dataclass
class Stats:
    """Latencies (s) and error counts of one kind of request."""

    latencies: list[float] = field(default_factory=list)
    errors: dict[str, int] = field(default_factory=dict)
    late: int = 0  # requests started more than 50 ms after their scheduled time (the client fell behind)

    def add(self, seconds: float, error: str | None) -> None:
        """Record one request."""
        if error is None:
            self.latencies.append(seconds)
        else:
            self.errors[error] = self.errors.get(error, 0) + 1

    def row(self, name: str, wall_s: float) -> str:
        """Return a Markdown table row."""
        lat = np.array(self.latencies) * 1000.0
        n_err = sum(self.errors.values())
        p50, p99, mx = (np.percentile(lat, 50), np.percentile(lat, 99), lat.max()) if len(lat) else (0, 0, 0)
        errs = ", ".join(f"{k} x{v}" for k, v in sorted(self.errors.items())) or "0"
        return (
            f"| {name} | {len(lat) + n_err} | {len(lat) / wall_s:.1f} | {p50:.1f} | {p99:.1f} | {mx:.1f} | "
            f"{errs} | {self.late} |"
        )


class Server:
    """redis-server (AOF) + `python -m cli.main serve` in a temp dir; stopped by stop()."""

    def __init__(self, workers: int, redis_url: str | None, api_workers: int = 1) -> None:
        self.tmp = Path(tempfile.mkdtemp(prefix="vm-load-"))
        self.port = free_port()
        self.redis: subprocess.Popen[bytes] | None = None
        self.redis_url = redis_url
        if not redis_url:
            rport = free_port()
            (self.tmp / "redis").mkdir()
            self.redis = subprocess.Popen(
                ["redis-server", "--port", str(rport), "--dir", str(self.tmp / "redis"), "--appendonly", "yes",
                 "--save", "", "--bind", "127.0.0.1"],
                stdout=subprocess.DEVNULL,
            )  # fmt: skip
            self.redis_url = f"redis://127.0.0.1:{rport}/0"
        env = service_env(
            self.tmp / "data",
            {KEY: ["ingest", "view", "admin"]},
            redis_url=self.redis_url,
            pythonpath=ROOT,
            log_level="WARNING",
            api_workers=str(api_workers),
        )
        self.serve = start_process(serve_command(self.port, workers), env, cwd=ROOT)
        self.base = f"http://127.0.0.1:{self.port}"

    def wait_ready(self, timeout_s: float = 90.0) -> None:
        """Block until /readyz answers 200."""
        wait_until_ready(f"{self.base}/readyz", timeout_s, [self.serve])

    def stop(self) -> None:
        """Stop serve, then Redis; remove the temp dir."""
        stop_processes([self.serve], 30.0)
        if self.redis is not None:
            self.redis.terminate()
            self.redis.wait()
        shutil.rmtree(self.tmp, ignore_errors=True)


async def create_session(http: httpx.AsyncClient, calibration: dict, t_end: float) -> str:
    """Create a session and send forces (1 N per sensor, 100 Hz) up to t_end; return its id."""
    resp = await http.post("/v1/sessions", json={"calibration": calibration, "label": "load"})
    resp.raise_for_status()
    sid = resp.json()["id"]
    t = np.arange(0.0, t_end, 0.01)
    samples = np.column_stack([t, np.ones((len(t), 4))]).tolist()
    for i in range(0, len(samples), 20_000):
        (await http.post(f"/v1/sessions/{sid}/forces", json={"samples": samples[i : i + 20_000]})).raise_for_status()
    return sid


async def upload(client: RawHttp, sid: str, seq: int, t_s: float, data: bytes, stats: Stats) -> None:
    """Upload one frame and record its latency."""
    meta = json.dumps({"seq": seq, "t_s": t_s}).encode()
    body, ctype = multipart({"image": (f"{seq}.png", "image/png", data), "meta": (None, "application/json", meta)})
    started = time.perf_counter()
    try:
        answer = await client.request("POST", f"/v1/sessions/{sid}/frames", body, ctype)
        err = None if answer.status in (200, 202) else str(answer.status)
    except (OSError, asyncio.IncompleteReadError) as exc:
        err = type(exc).__name__
    stats.add(time.perf_counter() - started, err)


async def uploaders(
    client: RawHttp, sids: list[str], frames: list[bytes], rate: float, seconds: float, stats: Stats
) -> None:
    """Start uploads at `rate` per second for `seconds` (open loop), round-robin over sessions."""
    t0 = time.perf_counter()
    tasks = []
    n = int(rate * seconds)
    for i in range(n):
        due = t0 + i / rate
        delay = due - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        elif delay < -0.05:
            stats.late += 1
        sid, k = sids[i % len(sids)], i // len(sids)
        tasks.append(asyncio.create_task(upload(client, sid, k, 0.1 * k, frames[k % len(frames)], stats)))
    await asyncio.gather(*tasks)


async def viewer(client: RawHttp, sid: str, rate: float, seconds: float, stats: Stats, rng: random.Random) -> None:
    """Read mosaic.json, then fetch random tiles (with their revision) at `rate` per second for `seconds`."""
    doc = json.loads((await client.request("GET", f"/v1/sessions/{sid}/mosaic.json")).body)
    names = list(doc["revisions"]["vein"].items())
    t0 = time.perf_counter()
    i = 0
    while time.perf_counter() - t0 < seconds:
        due = t0 + i / rate + rng.uniform(0, 1 / rate)
        await asyncio.sleep(max(0.0, due - time.perf_counter()))
        name, rev = rng.choice(names)
        level, rest = name.split("/")
        started = time.perf_counter()
        try:
            answer = await client.request("GET", f"/v1/sessions/{sid}/mosaic_files/{level}/{rest}.png?rev={rev}&v=1")
            err = None if answer.status == 200 else str(answer.status)
        except (OSError, asyncio.IncompleteReadError) as exc:
            err = type(exc).__name__
        stats.add(time.perf_counter() - started, err)
        i += 1


def _children(pid: int) -> list[int]:
    kids: list[int] = []
    with contextlib.suppress(OSError):
        for tid in os.listdir(f"/proc/{pid}/task"):
            kids.extend(int(k) for k in Path(f"/proc/{pid}/task/{tid}/children").read_text().split())
    return kids


def _cpu_s(pid: int) -> float:
    with contextlib.suppress(OSError, ValueError, IndexError):
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime
    return 0.0


def process_cpu_s(root_pid: int, match: str) -> float:
    """Return the CPU seconds (user + system) used so far by root_pid's descendants whose command line has
    `match`, and by all of their own descendants (uvicorn's worker processes)."""
    total, stack, seen = 0.0, [(root_pid, False)], set()
    while stack:
        pid, inside = stack.pop()
        if pid in seen:
            continue
        seen.add(pid)
        if not inside and pid != root_pid:
            with contextlib.suppress(OSError):
                inside = match in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        if inside:
            total += _cpu_s(pid)
        stack.extend((kid, inside) for kid in _children(pid))
    return total


async def run(args: argparse.Namespace, base: str, serve_pid: int) -> tuple[Stats, Stats, float, dict, float, float]:
    """Prepare a finished session for the viewers, then run uploaders and viewers together."""
    scan = simulate("short", 1)
    frames = [cv2.imencode(".png", scan.frame(i))[1].tobytes() for i in range(len(scan))]
    calibration = scan.calibration.to_dict()
    limits = httpx.Limits(max_connections=args.connections, max_keepalive_connections=args.connections)
    headers = {"Authorization": f"Bearer {KEY}"}
    async with httpx.AsyncClient(base_url=base, headers=headers, timeout=30.0, limits=limits) as http:
        view_sid = await create_session(http, calibration, 0.1 * len(frames) + 1)
        warm = Stats()
        client = RawHttp(http.base_url.host, http.base_url.port, headers, args.connections)
        await asyncio.gather(*(upload(client, view_sid, i, 0.1 * i, frames[i], warm) for i in range(len(frames))))
        await http.post(f"/v1/sessions/{view_sid}/finish")
        deadline = time.monotonic() + 300
        while (await http.get(f"/v1/sessions/{view_sid}")).json()["status"] != "done":
            if time.monotonic() > deadline:
                raise RuntimeError("the viewers' session did not finish")
            await asyncio.sleep(0.5)
        per_session = int(args.upload_rate * args.seconds / args.sessions) + 1
        sids = [await create_session(http, calibration, 0.1 * per_session + 1) for _ in range(args.sessions)]
        up, tiles = Stats(), Stats()
        rng = random.Random(0)
        cpu0, gen0 = process_cpu_s(serve_pid, "uvicorn"), time.process_time()
        t0 = time.perf_counter()
        await asyncio.gather(
            uploaders(client, sids, frames, args.upload_rate, args.seconds, up),
            *(viewer(client, view_sid, args.tile_rate, args.seconds, tiles, rng) for _ in range(args.viewers)),
        )
        wall = time.perf_counter() - t0
        api_cpu = process_cpu_s(serve_pid, "uvicorn") - cpu0
        gen_cpu = time.process_time() - gen0
        await client.close()
        state = (await http.get(f"/v1/sessions/{sids[0]}")).json()
    return up, tiles, wall, state, api_cpu, gen_cpu


def _loop_factory():
    """Return uvloop's event loop class when installed (as uvicorn uses it), else None (asyncio's own)."""
    try:
        import uvloop
    except ImportError:
        return None
    return uvloop.new_event_loop


def main(argv: list[str] | None = None) -> int:
    """Run the load test and print the table."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--upload-rate", type=float, default=200.0, help="frame uploads started per second")
    p.add_argument("--sessions", type=int, default=None, help="upload sessions (default: one per 10 frames/s)")
    p.add_argument("--viewers", type=int, default=32)
    p.add_argument("--tile-rate", type=float, default=5.0, help="tile requests per second per viewer")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--api-workers", type=int, default=1, help="API processes (setting api_workers)")
    p.add_argument("--connections", type=int, default=256, help="client connection pool size")
    p.add_argument("--redis-url", default=None, help="default: a private redis-server with AOF")
    args = p.parse_args(argv)
    if args.sessions is None:
        args.sessions = max(1, math.ceil(args.upload_rate / 10))
    server = Server(args.workers, args.redis_url, args.api_workers)
    try:
        server.wait_ready()
        runner = asyncio.Runner(loop_factory=_loop_factory())
        with runner:
            up, tiles, wall, state, api_cpu, gen_cpu = runner.run(run(args, server.base, server.serve.pid))
    finally:
        server.stop()
    print(
        f"\n{os.cpu_count()} CPUs; {args.upload_rate:g} uploads/s offered over {args.sessions} sessions, "
        f"{args.viewers} viewers x {args.tile_rate:g} tiles/s, {args.seconds:g} s, {args.workers} workers, "
        f"{args.api_workers} API process(es)\n"
    )
    print("| requests | sent | ok/s | p50 ms | p99 ms | max ms | errors | started late |")
    print("|---|---:|---:|---:|---:|---:|---|---:|")
    print(up.row("frame uploads (640x480 PNG)", wall))
    print(tiles.row("Deep Zoom tiles", wall))
    # requests the server answered (a client-side timeout may never have reached it)
    requests = sum(len(st.latencies) + sum(n for k, n in st.errors.items() if k.isdigit()) for st in (up, tiles))
    print(
        f"\nAPI process(es) CPU during the run: {api_cpu:.2f} s = {1000 * api_cpu / max(1, requests):.1f} ms per "
        f"request ({requests} answered; with --viewers 0 that is the CPU cost of one upload)"
    )
    print(f"load generator CPU during the run: {gen_cpu:.2f} s ({100 * gen_cpu / wall:.0f} % of a core)")
    received, processed = state["frames_received"], state["frames_processed"]
    print(f"\nfirst upload session when the load stopped: {received} frames received, {processed} processed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
