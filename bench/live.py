"""Live benchmark: does the running service keep up with a probe uploading at --rate frames/s (issue 6)?

    .venv/bin/python bench/live.py [--frames 150] [--rate 10] [--baseline-rate 5] [--scenario raster] [--seed 1]

Starts the service as `veinmosaic serve` does (cli.launcher.Service: API + --workers workers, an embedded
Redis unless REDIS_URL is set, then under a private key prefix that is deleted afterwards) on a temporary
data dir, simulates the scan (640x480 realistic frames) and uploads its first --frames frames with
cli.client.upload_scan_folder: forces interleaved ahead of each frame as the probe sends them, frames paced
on the scan's own clock scaled to a mean of --rate frames/s (0: as fast as the server accepts). Meanwhile it
polls GET /v1/sessions/{id} every --poll s. Frames are registered in seq order, so frame s counts as
processed at the first poll with frames_processed > s; its lag is that time minus its upload's 2xx
(resolution: the poll interval plus the workers' flush interval). The steady part is the second half: the
processing rate between the counter's steps reaching 50 % and 90 % of the frames, the backlog's linear trend
over the second half of the uploads (the live pipeline prepares nothing before it holds frames 0-23, whose
window mask it needs, so the first frames' lag includes that wait). One row for the baseline rate, one for
--rate; keeps up when processing >= 95 % of the upload rate and the trend stays under 5 % of it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import secrets
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import httpx
import numpy as np
import redis
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cli.client import ApiError, VeinmosaicClient, upload_scan_folder
from cli.launcher import Service, free_port
from services.core.inputs.scan import Scan
from services.core.simulation.scenarios import ALL_SCENARIOS, LONG_SCENARIOS, simulate
from services.settings import get_settings
from services.store.scan_folder import write_scan_folder

TOLERANCE = 0.05  # processing may trail the upload rate by this fraction; the backlog may grow this fast
STEADY = 0.5  # the steady part starts half way through the frames (the start-up waits for 24 frames, see below)


class TimedClient(VeinmosaicClient):
    """The product's client, noting when each frame upload got its 2xx."""

    def __init__(self, base_url: str, key: str) -> None:
        super().__init__(base_url, key)
        self.acked: dict[int, float] = {}

    def upload_frame(self, session_id: str, seq: int, t_s: float, data: bytes, filename: str) -> int:
        """Upload one frame and record the monotonic time of its 2xx."""
        status = super().upload_frame(session_id, seq, t_s, data, filename)
        self.acked[seq] = time.monotonic()
        return status


@dataclass
class Row:
    """One run's figures (times in seconds, rates in frames/s)."""

    label: str
    rate_set: float
    frames: int
    upload_rate: float
    proc_rate: float
    lag: np.ndarray
    backlog_end: int
    backlog_trend: float
    drain_s: float
    done_s: float
    registered: float
    session_id: str = ""
    status: str = ""  # the session's last polled status
    rmse_mm: float = float("nan")  # its path against the scan's reference.csv (with_rmse), once done

    @property
    def keeps_up(self) -> bool:
        """Return True when processing matches the uploads within TOLERANCE and the backlog does not grow."""
        ok_rate = self.proc_rate >= (1 - TOLERANCE) * self.upload_rate
        return bool(ok_rate and self.backlog_trend <= TOLERANCE * self.upload_rate and np.isfinite(self.drain_s))

    def cells(self) -> list[str]:
        """Return the table cells of this row."""
        p50, p95, top = (np.percentile(self.lag, q) for q in (50, 95, 100)) if self.lag.size else (np.nan,) * 3
        rate_set = f"{self.rate_set:g}" if self.rate_set > 0 else "max"
        return [
            self.label, rate_set, str(self.frames), f"{self.upload_rate:.2f}", f"{self.proc_rate:.2f}",
            f"{self.proc_rate / self.upload_rate:.2f}", f"{p50:.2f}", f"{p95:.2f}", f"{top:.2f}",
            str(self.backlog_end), f"{self.backlog_trend:+.2f}", f"{self.drain_s:.2f}", f"{self.done_s:.2f}",
            f"{100 * self.registered:.1f}", "yes" if self.keeps_up else "no",
        ]  # fmt: skip


HEADER = [
    "run", "rate set", "frames", "upload f/s", "proc f/s", "proc/upload", "lag p50 s", "lag p95 s", "lag max s",
    "backlog at end", "backlog trend f/s", "drain s", "done s", "registered %", "keeps up",
]  # fmt: skip


def first_frames(scan: Scan, n: int) -> Scan:
    """Return the scan's first n frames with the force/IMU samples the probe sends until then."""
    n = min(n, len(scan))
    t_end = float(scan.frame_t_s[n - 1]) + 0.5
    keep_f = scan.force_t_s <= t_end
    keep_i = None if scan.imu_t_s is None else scan.imu_t_s <= t_end
    return replace(
        scan,
        frame_seq=scan.frame_seq[:n],
        frame_t_s=scan.frame_t_s[:n],
        force_t_s=scan.force_t_s[keep_f],
        forces_n=scan.forces_n[keep_f],
        imu_t_s=None if keep_i is None else scan.imu_t_s[keep_i],
        imu_tilt_deg=None if keep_i is None or scan.imu_tilt_deg is None else scan.imu_tilt_deg[keep_i],
        reference_mm=None if scan.reference_mm is None else scan.reference_mm[:n],
        reference_angles_deg=None if scan.reference_angles_deg is None else scan.reference_angles_deg[:n],
        truth={},
    )


def run(
    service: Service, key: str, scan_dir: Path, scan: Scan, rate: float, label: str, args: argparse.Namespace
) -> Row:
    """Upload the scan folder at `rate` frames/s into a new session while polling its state; return its figures."""
    n = len(scan)
    recorded = (scan.frame_t_s[-1] - scan.frame_t_s[0]) / max(1, n - 1)  # the scan's mean frame interval
    client = TimedClient(service.base_url, key)
    watcher = VeinmosaicClient(service.base_url, key, timeout_s=5.0, max_retries=0)  # a poll never blocks long
    samples: list[tuple[float, int, str]] = []  # (time of the answer, frames_processed, status)
    final: dict = {}
    bar = tqdm(total=n, desc=f"{label} @ {rate:g} f/s", unit="frame", file=sys.stderr, dynamic_ncols=True)
    deadline = time.monotonic() + (n / rate if rate > 0 else 0) + args.timeout
    halt = threading.Event()

    def poll(sid: str) -> None:
        while not halt.is_set() and time.monotonic() < deadline:
            if any(proc.poll() is not None for proc in service.processes):
                final["crashed"] = True  # a bench reports a dead API or worker instead of restarting it
                return
            with contextlib.suppress(httpx.HTTPError, ApiError):
                state = watcher.session(sid)
                samples.append((time.monotonic(), int(state["frames_processed"]), state["status"]))
                final.update(state)
                bar.n = int(state["frames_processed"])
                bar.set_postfix(uploaded=len(client.acked), refresh=True)
                if state["status"] in ("done", "failed"):
                    return
            halt.wait(args.poll)

    poller: list[threading.Thread] = []

    created_ids: list[str] = []

    def started(created: dict) -> None:
        created_ids.append(created["id"])
        poller.append(threading.Thread(target=poll, args=(created["id"],), daemon=True))
        poller[0].start()

    try:
        upload_scan_folder(client, scan_dir, label="bench", realtime=rate * recorded, on_session=started)
        poller[0].join(max(0.0, deadline - time.monotonic()) + 10.0)
    finally:
        halt.set()
        for thread in poller:
            thread.join(10.0)
        bar.close()
        client.close()
        watcher.close()
    if final.get("crashed"):
        raise RuntimeError(f"{label}: a service process exited during the run")
    if not samples:
        raise RuntimeError(f"{label}: GET /v1/sessions/{{id}} never answered")
    acked = np.array([client.acked[int(s)] for s in scan.frame_seq])
    row = measure(label, rate, acked, samples, final, args.frames_csv)
    return replace(row, session_id=created_ids[0], status=str(final.get("status", "")))


def with_rmse(service: Service, key: str, row: Row, scan_dir: Path) -> Row:
    """Return the row with the RMSE (mm) of its done session's path against the scan folder's reference.csv, as
    the service's accuracy report gives it (POST /v1/sessions/{id}/reference; run after every upload of a bench,
    so that the report's work delays none); NaN when not done or the folder has none."""
    reference = scan_dir / "reference.csv"
    if row.status != "done" or not reference.is_file():
        return row
    client = VeinmosaicClient(service.base_url, key, timeout_s=60.0)
    try:
        rmse = client.post_reference(row.session_id, reference.read_text(encoding="utf-8")).get("rmse_mm")
    finally:
        client.close()
    return replace(row, rmse_mm=float("nan") if rmse is None else float(rmse))


def measure(
    label: str, rate: float, acked: np.ndarray, samples: list[tuple[float, int, str]], final: dict, csv: Path | None
) -> Row:
    """Return a run's figures from each frame's 2xx time (in seq order) and the polled (time, processed, status)."""
    n = len(acked)
    ts = np.array([s[0] for s in samples])
    processed = np.maximum.accumulate(np.array([s[1] for s in samples]))
    at = np.searchsorted(processed, np.arange(1, n + 1), side="left")  # first poll that saw frame s processed
    t_proc = np.where(at < len(ts), ts[np.minimum(at, len(ts) - 1)], np.nan)
    t_first, t_last = float(acked.min()), float(acked.max())
    # steady rate between the counter's steps (workers report at flushes) that reach STEADY and 90 % of the frames
    steps = np.flatnonzero(np.diff(processed, prepend=0) > 0)
    lo, hi = (steps[processed[steps] >= q * n][:1] for q in (STEADY, 0.9))
    lo, hi = (lo[0] if lo.size else -1), (hi[0] if hi.size else (steps[-1] if steps.size else -1))
    proc_rate = (processed[hi] - processed[lo]) / (ts[hi] - ts[lo]) if 0 <= lo < hi else np.nan
    backlog = np.searchsorted(np.sort(acked), ts, side="right") - processed
    window = (ts >= t_first + STEADY * (t_last - t_first)) & (ts <= t_last)
    trend = float(np.polyfit(ts[window], backlog[window], 1)[0]) if window.sum() >= 3 else np.nan
    after = np.flatnonzero(ts >= t_last)
    done = [t for t, _, st in samples if st == "done"]
    if csv:  # per frame: when its upload got its 2xx and when a poll first saw it processed
        with open(csv, "a") as f:
            f.writelines(
                f"{label},{rate:g},{s},{a - t_first:.3f},{p - t_first:.3f}\n"
                for s, (a, p) in enumerate(zip(acked, t_proc, strict=True))
            )
    registered = final.get("registered_fraction")
    if registered is None:  # no results served yet: the live counters
        registered = 1 - final.get("frames_lost", 0) / max(1, final.get("frames_processed", 0))
    return Row(
        label=label,
        rate_set=rate,
        frames=n,
        upload_rate=(n - 1) / (t_last - t_first) if t_last > t_first else np.nan,
        proc_rate=float(proc_rate),
        lag=(t_proc - acked)[np.isfinite(t_proc)],
        backlog_end=int(n - processed[after[0]]) if after.size else n,
        backlog_trend=trend,
        drain_s=float(t_proc[-1] - t_last),
        done_s=done[0] - t_last if done else np.nan,
        registered=float(registered),
    )


def main(argv: list[str] | None = None) -> int:
    """Start the service, run the baseline and target rates, print the table; return 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="raster", choices=[s for s in ALL_SCENARIOS if s != "calib"])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--frames", type=int, default=150, help="upload the scan's first N frames")
    p.add_argument("--rate", type=float, default=10.0, help="target upload rate, frames/s (0: as fast as accepted)")
    p.add_argument("--baseline-rate", type=float, default=5.0, help="rate of the comparison row (<0: none)")
    p.add_argument("--workers", type=int, default=2, help="worker processes")
    p.add_argument("--poll", type=float, default=0.1, help="seconds between GET /v1/sessions/{id}")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds allowed after the uploads' schedule")
    p.add_argument("--frames-csv", type=Path, help="append run,rate,seq,t_2xx_s,t_processed_s rows to this file")
    args = p.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # SIGTERM cleans up like Ctrl-C
    key = "bench-" + secrets.token_urlsafe(24)
    redis_url = get_settings().redis_url
    prefix = f"vmbench:{secrets.token_hex(6)}:"
    level = os.environ.get("VEINMOSAIC_LOG_LEVEL", "WARNING")  # INFO shows take-overs and releases
    env = {"VEINMOSAIC_API_KEYS": json.dumps({key: ["ingest", "view"]}), "VEINMOSAIC_LOG_LEVEL": level}
    if redis_url:  # a shared server: our own keys only, deleted at the end
        env["VEINMOSAIC_REDIS_PREFIX"] = prefix
    print(f"simulating {args.scenario} seed {args.seed} ...", file=sys.stderr)
    length = args.frames if args.scenario in LONG_SCENARIOS else None  # an exam is simulated as long as asked
    scan = first_frames(simulate(args.scenario, args.seed, frames=length), args.frames)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="vm-live-", ignore_cleanup_errors=True) as tmp:
        scan_dir = Path(tmp) / "scan"
        write_scan_folder(scan, scan_dir)
        data = Path(tmp) / "data"
        service = Service(data, port=free_port(), workers=args.workers, redis_url=redis_url, extra_env=env)
        try:
            service.start()
            if args.baseline_rate >= 0:
                rows.append(run(service, key, scan_dir, scan, args.baseline_rate, "baseline", args))
            rows.append(run(service, key, scan_dir, scan, args.rate, "target", args))
        finally:
            service.stop()
            if redis_url:
                with contextlib.closing(redis.Redis.from_url(redis_url)) as r:
                    for k in r.scan_iter(match=f"{prefix}*", count=1000):
                        r.delete(k)
    h, w = scan.frame(0).shape
    where = "REDIS_URL" if redis_url else "embedded"
    print(
        f"\n{args.scenario} seed {args.seed}, {w}x{h}, {len(scan)} frames; {args.workers} workers, "
        f"{os.cpu_count()} CPUs, Redis {where}; lag resolution ~{args.poll:g} s poll + the workers' flush interval\n"
    )
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for row in rows:
        print("| " + " | ".join(row.cells()) + " |")
    if len(rows) == 2 and rows[0].proc_rate > 0:
        print(f"\ntarget / baseline processing rate: {rows[1].proc_rate / rows[0].proc_rate:.2f}")
    print(f"keeps up with {args.rate:g} frames/s: {'yes' if rows[-1].keeps_up else 'no'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
