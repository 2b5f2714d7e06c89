"""Peak memory of a real API process, and how fast it refuses hostile input (issue 8).

Starts the API alone (uvicorn subprocess via cli.launcher.Service with no workers; Redis at REDIS_URL or the
embedded one), creates a 640x480 session, then sends in turn: PNG bombs (a ~1 kB PNG claiming 30000x30000, and
one claiming the calibrated size but colour), an oversize frame upload (21 MB declared, over the limit), a
19 MB frame of garbage (under the limit: read whole, then refused), a 200 MB
JSON body with Transfer-Encoding: chunked, a 200 MB body declared by Content-Length, and racing uploads (16
threads sending valid 640x480 frames and bombs together, /healthz timed meanwhile). RSS of the API process is
sampled every 5 ms; a refusal's latency runs from sending the request to its answer. Prints one table.
Targets (issue 8): peak RSS under 400 MB, refusals under 100 ms.

    python bench/api_memory.py [--rounds 5]
"""

from __future__ import annotations

import argparse
import json
import os
import select
import socket
import statistics
import struct
import tempfile
import threading
import time
import uuid
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import httpx
import numpy as np
import psutil

from cli.launcher import Service, free_port

KEY = f"bench-{uuid.uuid4().hex}"
W, H = 640, 480
CALIBRATION = {
    "image_size": [W, H],
    "camera_matrix": [[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]],
    "px_per_mm": 8.0,
}


def png_claiming(width: int, height: int, colour_type: int = 0) -> bytes:
    """Return a small valid PNG whose header claims width x height pixels (zeros compress ~1000:1)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 1_000_000, 9))
        + chunk(b"IEND", b"")
    )


class RssSampler:
    """Samples a process's RSS (MB) every 5 ms in a thread; `peak` since the last reset."""

    def __init__(self, pid: int) -> None:
        self.proc = psutil.Process(pid)
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.peak = max(self.peak, self.proc.memory_info().rss / 2**20)
            except psutil.Error:
                return
            time.sleep(0.005)

    def reset(self) -> float:
        """Return the current RSS and restart the peak from it."""
        now = self.proc.memory_info().rss / 2**20
        self.peak = now
        return now

    def stop(self) -> None:
        """Stop sampling."""
        self._stop.set()
        self._thread.join()


def raw_post(base_url: str, path: str, head_extra: str, total: int, chunked: bool) -> tuple[int, float]:
    """POST `total` bytes of spaces (chunked or with Content-Length) until the server answers.

    Returns (status, seconds from the first byte sent to the status line).
    """
    host, port = base_url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=30)
    started = time.perf_counter()
    try:
        framing = "Transfer-Encoding: chunked" if chunked else f"Content-Length: {total}"
        sock.sendall(
            (
                f"POST {path} HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer {KEY}\r\n{head_extra}{framing}\r\n\r\n"
            ).encode()
        )
        block = 64 * 1024
        payload = (f"{block:x}\r\n".encode() + b" " * block + b"\r\n") if chunked else b" " * block
        sent = 0
        while sent < total and not select.select([sock], [], [], 0)[0]:  # stop sending once an answer is in
            try:
                sock.sendall(payload)  # whole chunks only: the framing stays valid
            except (BrokenPipeError, ConnectionResetError):
                break
            sent += block
        answer = b""
        while b"\r\n" not in answer:
            more = sock.recv(65536)
            if not more:
                break
            answer += more
        elapsed = time.perf_counter() - started
        return int(answer.split(b" ", 2)[1]), elapsed
    finally:
        sock.close()


def timed(call: Callable[[], int]) -> tuple[int, float]:
    """Return (status, seconds) of one call."""
    started = time.perf_counter()
    status = call()
    return status, time.perf_counter() - started


def main() -> None:
    """Run the scenarios and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="repetitions of each scenario")
    args = parser.parse_args()
    env = {
        "VEINMOSAIC_API_KEYS": json.dumps({KEY: ["ingest", "view", "admin"]}),
        "VEINMOSAIC_REDIS_PREFIX": f"vmbench{uuid.uuid4().hex[:8]}:",
        "VEINMOSAIC_LOG_LEVEL": "WARNING",
    }
    with tempfile.TemporaryDirectory() as tmp:
        service = Service(
            Path(tmp) / "data", port=free_port(), workers=0, redis_url=os.environ.get("REDIS_URL"), extra_env=env
        )
        with service:
            run(service, args.rounds)


def run(service: Service, rounds: int) -> None:
    """Measure every scenario against the running API."""
    url = service.base_url
    http = httpx.Client(base_url=url, headers={"Authorization": f"Bearer {KEY}"}, timeout=60)
    sampler = RssSampler(service.pids()["api"])
    sid = http.post("/v1/sessions", json={"calibration": CALIBRATION}).json()["id"]
    frames = [
        cv2.imencode(".png", np.random.default_rng(i).integers(0, 255, (H, W), np.uint8))[1].tobytes()
        for i in range(64)
    ]
    bomb = png_claiming(30000, 30000)
    colour_bomb = png_claiming(W, H, colour_type=2)
    garbage = b"\x89PNG\r\n\x1a\n" + b"\0" * (19 * 2**20)  # under max_frame_bytes: read, sniffed, refused
    seq = iter(range(10**6))

    def frame(data: bytes, t_s: float = 0.0) -> int:
        files = {"image": ("f.png", data, "image/png")}
        return http.post(
            f"/v1/sessions/{sid}/frames", files=files, data={"meta": json.dumps({"seq": next(seq), "t_s": t_s})}
        ).status_code

    # warm up (imports, first decode, Redis connection) before measuring
    for i in range(4):
        frame(frames[i], 0.1 * i)
    baseline = sampler.reset()
    rows: list[tuple[str, str, float, float, float]] = []

    def scenario(name: str, call: Callable[[], tuple[int, float]]) -> None:
        sampler.reset()
        results = [call() for _ in range(rounds)]
        statuses = sorted({s for s, _ in results})
        times_ms = [t * 1000 for _, t in results]
        rows.append((name, ",".join(map(str, statuses)), statistics.median(times_ms), max(times_ms), sampler.peak))

    scenario("PNG bomb 30000x30000 (1 kB)", lambda: timed(lambda: frame(bomb)))
    scenario("PNG 640x480 header, colour", lambda: timed(lambda: frame(colour_bomb)))
    multipart = "Content-Type: multipart/form-data; boundary=x\r\n"
    scenario(
        "oversize frame upload 21 MB (Content-Length)",
        lambda: raw_post(url, f"/v1/sessions/{sid}/frames", multipart, 21 * 2**20, chunked=False),
    )
    scenario("19 MB frame of garbage (read whole, then refused)", lambda: timed(lambda: frame(garbage)))
    scenario(
        "200 MB JSON, chunked",
        lambda: raw_post(url, "/v1/sessions", "Content-Type: application/json\r\n", 200 * 2**20, chunked=True),
    )
    scenario(
        "200 MB JSON, Content-Length",
        lambda: raw_post(url, "/v1/sessions", "Content-Type: application/json\r\n", 200 * 2**20, chunked=False),
    )

    # racing: 16 threads, valid frames and bombs interleaved, plus health checks timed meanwhile
    sampler.reset()
    health_ms: list[float] = []
    stop = threading.Event()

    def probe() -> None:
        with httpx.Client(base_url=url, timeout=30) as h:
            while not stop.is_set():
                started = time.perf_counter()
                h.get("/healthz")
                health_ms.append((time.perf_counter() - started) * 1000)
                time.sleep(0.01)

    prober = threading.Thread(target=probe)
    prober.start()
    racing_started = time.perf_counter()
    jobs = [frames[i % len(frames)] if i % 2 == 0 else bomb for i in range(16 * rounds)]
    with ThreadPoolExecutor(16) as pool:
        outcomes = list(pool.map(lambda d: timed(lambda: frame(d, 0.2)), jobs))
    racing_s = time.perf_counter() - racing_started
    stop.set()
    prober.join()
    refused = [t * 1000 for s, t in outcomes if s >= 400]
    accepted = [t * 1000 for s, t in outcomes if s < 400]
    rows.append(
        (
            f"racing: {len(accepted)} frames + {len(refused)} bombs, 16 threads",
            ",".join(map(str, sorted({s for s, _ in outcomes}))),
            statistics.median(refused),
            max(refused),
            sampler.peak,
        )
    )
    sampler.stop()
    http.close()

    print(f"API process RSS after warm-up: {baseline:.0f} MB; rounds per scenario: {rounds}\n")
    print("| input | status | refusal median ms | refusal max ms | peak RSS MB |")
    print("|---|---|---:|---:|---:|")
    for name, statuses, med, worst, peak in rows:
        print(f"| {name} | {statuses} | {med:.1f} | {worst:.1f} | {peak:.0f} |")
    print(
        f"\nracing: accepted frames median {statistics.median(accepted):.1f} ms; wall {racing_s:.2f} s; "
        f"/healthz meanwhile median {statistics.median(health_ms):.1f} ms, max {max(health_ms):.1f} ms "
        f"({len(health_ms)} probes)"
    )


if __name__ == "__main__":
    main()
