"""CPU cost per request of the API alone: a bare uvicorn process (no workers, no viewers), driven over loopback.

    python bench/api_cost.py [--uploads 1500] [--in-flight 8]

For each HTTP stack (uvicorn's h11 + asyncio as the baseline, then httptools + uvloop, what the service runs
when they are installed) it starts the API, creates a 640x480 session and times /healthz, GET /v1/sessions/{id}
and frame uploads (640x480 PNG of the simulated short scan, `--in-flight` at once), reading the API process's
CPU time from /proc. Prints one table: requests/s, CPU ms per request (user + system) and the ratio of CPU per
request against the baseline stack in the same run. Redis: REDIS_URL (a private key prefix, deleted at the
end) or the embedded one.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import sys
import tempfile
import time
import uuid
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.raw_http import RawHttp, multipart  # noqa: E402
from cli.launcher import api_command, free_port, service_env, start_process, stop_processes, wait_until_ready  # noqa: E402
from services.core.simulation.scenarios import simulate  # noqa: E402
from services.jobs.redis_backend import close, connect  # noqa: E402

KEY = "api-cost-key-0123456789abcdef"
STACKS = {
    "h11 + asyncio (baseline)": ["--http", "h11", "--loop", "asyncio"],
    "httptools + uvloop": ["--http", "httptools", "--loop", "uvloop"],
}


def cpu_s(pid: int) -> tuple[float, float]:
    """Return (user, system) CPU seconds used so far by process pid (all its threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick


async def timed(pid: int, n: int, in_flight: int, make) -> tuple[float, float, float]:
    """Send n requests (in_flight at once) made by make(i); return (requests/s, user ms, system ms per request)."""
    slots = asyncio.Semaphore(in_flight)

    async def one(i: int) -> None:
        async with slots:
            answer = await make(i)
            if answer.status >= 300:
                raise RuntimeError(f"request {i} answered {answer.status}")

    (u0, s0), t0 = cpu_s(pid), time.perf_counter()
    await asyncio.gather(*(one(i) for i in range(n)))
    wall, (u1, s1) = time.perf_counter() - t0, cpu_s(pid)
    return n / wall, 1000 * (u1 - u0) / n, 1000 * (s1 - s0) / n


async def measure(pid: int, port: int, calibration: dict, frames: list[bytes], args: argparse.Namespace) -> dict:
    """Return {route: (requests/s, user ms, system ms)} for one running API."""
    client = RawHttp("127.0.0.1", port, {"Authorization": f"Bearer {KEY}"}, args.in_flight)
    body = json.dumps({"calibration": calibration, "label": "cost"}).encode()
    sid = json.loads((await client.request("POST", "/v1/sessions", body, "application/json")).body)["id"]
    samples = [[0.01 * i, 1.0, 1.0, 1.0, 1.0] for i in range(args.uploads * 10 + 100)]  # 100 Hz over the frames
    for k in range(0, len(samples), 20_000):  # the API takes at most 20000 rows a batch
        batch = json.dumps({"samples": samples[k : k + 20_000]}).encode()
        answer = await client.request("POST", f"/v1/sessions/{sid}/forces", batch, "application/json")
        if answer.status != 202:
            raise RuntimeError(f"forces answered {answer.status}")

    def upload(i: int):
        meta = json.dumps({"seq": i, "t_s": 0.1 * i}).encode()
        data, ctype = multipart(
            {"image": ("f.png", "image/png", frames[i % len(frames)]), "meta": (None, "application/json", meta)}
        )
        return client.request("POST", f"/v1/sessions/{sid}/frames", data, ctype)

    out = {
        "GET /healthz": await timed(pid, 2000, args.in_flight, lambda i: client.request("GET", "/healthz")),
        "GET /v1/sessions/{id}": await timed(
            pid, 1000, args.in_flight, lambda i: client.request("GET", f"/v1/sessions/{sid}")
        ),
        "POST frames (640x480 PNG)": await timed(pid, args.uploads, args.in_flight, upload),
    }
    await client.close()
    return out


def main(argv: list[str] | None = None) -> int:
    """Run every stack in turn and print the table."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--uploads", type=int, default=1500)
    p.add_argument("--in-flight", type=int, default=8, help="requests in flight at once")
    args = p.parse_args(argv)
    scan = simulate("short", 1)
    frames = [cv2.imencode(".png", scan.frame(i))[1].tobytes() for i in range(len(scan))]
    redis_url = os.environ.get("REDIS_URL")
    results = {}
    for name, flags in STACKS.items():
        tmp = Path(tempfile.mkdtemp(prefix="vm-api-cost-"))
        prefix = f"vmcost:{uuid.uuid4().hex[:8]}:"
        env = service_env(tmp / "data", {KEY: ["ingest", "view", "admin"]}, redis_url=redis_url, pythonpath=ROOT,
                          log_level="WARNING", redis_prefix=prefix)  # fmt: skip
        port = free_port()
        api = start_process(api_command("127.0.0.1", port) + flags, env, cwd=ROOT)
        try:
            wait_until_ready(f"http://127.0.0.1:{port}/readyz", 90, [api])
            results[name] = asyncio.run(measure(api.pid, port, scan.calibration.to_dict(), frames, args))
        finally:
            stop_processes([api])
            if redis_url:
                r = connect(redis_url, tmp)
                keys = list(r.scan_iter(match=f"{prefix}*", count=1000))
                if keys:
                    r.delete(*keys)
                close(r)
            shutil.rmtree(tmp, ignore_errors=True)
    base = results[next(iter(STACKS))]
    print(f"\n{os.cpu_count()} CPUs; API alone (1 uvicorn process, no workers), {args.in_flight} requests in flight\n")
    print("| stack | request | requests/s | CPU ms/request | user ms | system ms | CPU vs baseline |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name, rows in results.items():
        for route, (rate, user, system) in rows.items():
            ratio = (user + system) / sum(base[route][1:])
            print(f"| {name} | {route} | {rate:.1f} | {user + system:.2f} | {user:.2f} | {system:.2f} | {ratio:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
