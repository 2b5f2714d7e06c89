"""Several probes at once (issue 15): does one small machine keep up with N probes at 10 frames/s each?

    .venv/bin/python bench/probes.py [--probes 1,3] [--frames 336] [--rate 10] [--workers 2] [--scenario raster]

Starts the service once as `veinmosaic serve` does (cli.launcher.Service: API + --workers workers, embedded Redis
unless REDIS_URL is set, then under a private key prefix deleted afterwards) and, for each N of --probes in turn,
uploads N sessions at once, each a simulated scan (different seeds; or the --scan folders, cycling) paced at --rate
frames/s on its own clock with bench/live.py's client (forces interleaved ahead of each frame, every upload's 2xx
timed, the session state polled). Per N it prints, per session and in total: processed frames/s, lag p50/p95 from
each upload's 2xx to a poll seeing it processed, the time from the last upload to status done, the RMSE of its path
against the scan's reference.csv (the service's accuracy report, asked once every session of the run is done), and
the CPU seconds per frame and peak resident memory of the API, of each worker process, of the embedded Redis and of
this bench's own client over the run (psutil): the client shares the two cores here, as a clinic's probes on their
own network would not. Then, from the service's own counters (GET /metrics), the share of frames placed as keyframes
and the workers' CPU per frame: preparing it, and registering it (with the paste and refinements it brings) split
into keyframes (described and matched) and tracked frames (aligned on a keyframe: always with --worker-config
'{"method_options": {"track_overlap": 0.85}}', and with `best` while a session is behind its uploads:
MethodOptions.track_overlap_behind), and each session's finish by part, with the frames it pasted again and the
finish runs ahead (--worker-config '{"finish_ahead_every_s": 10}'). The first N (1 by default) is the baseline the
others are compared with in the same run. Targets (issue 15): 3 probes, every session done within 5 s of its last
upload and lag p95 <= 2 s; --rate 30 is one probe at 30 frames/s (issue 32).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import secrets
import signal
import sys
import tempfile
import threading
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import psutil
import redis
from prometheus_client.parser import text_string_to_metric_families

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from live import Row, first_frames, run, with_rmse  # bench/live.py: one paced session and its figures

from cli.launcher import Service, free_port
from services.core.session_reconstruction import KEYFRAME, TRACKED, UNPLACED
from services.core.simulation.scenarios import ALL_SCENARIOS, LONG_SCENARIOS, simulate
from services.jobs.redis_backend import embedded_pid
from services.settings import get_settings
from services.store.scan_folder import read_scan_folder, write_scan_folder

DONE_TARGET_S = 5.0
LAG_P95_TARGET_S = 2.0
KINDS = (KEYFRAME, TRACKED)  # SessionReconstruction.frame_kind of placed frames


def service_counters(service: Service) -> dict[str, float]:
    """Return the service's counters as GET /metrics exposes them, by metrics-hash field (frames_keyframe_total,
    prepare_cpu_seconds_total, ...)."""
    with urllib.request.urlopen(f"{service.base_url}/metrics", timeout=10) as answer:
        text = answer.read().decode()
    return {
        sample.name.removeprefix("veinmosaic_"): float(sample.value)
        for family in text_string_to_metric_families(text)
        for sample in family.samples
        if sample.name.endswith("_total")
    }


def cost_line(n: int, before: dict[str, float], after: dict[str, float], workers_cpu_s: float, frames_in: int) -> str:
    """Return a table row: the keyframe share and the workers' CPU ms per frame, prepared and registered by kind,
    and the rest of the workers' CPU (psutil's over the run: flushes, the finish, the queue) per frame uploaded."""
    delta = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in after}
    frames = {kind: delta.get(f"frames_{kind}_total", 0.0) for kind in KINDS}
    placed = sum(frames.values())
    prepared = delta.get("frames_prepared_total", 0.0)
    prepare_ms = 1000 * delta.get("prepare_cpu_seconds_total", 0.0) / prepared if prepared else math.nan
    register_ms = {
        kind: 1000 * delta.get(f"register_{kind}_cpu_seconds_total", 0.0) / frames[kind] if frames[kind] else math.nan
        for kind in KINDS
    }
    share = 100 * frames[KEYFRAME] / placed if placed else math.nan
    counted = delta.get("prepare_cpu_seconds_total", 0.0) + sum(
        delta.get(f"register_{kind}_cpu_seconds_total", 0.0) for kind in (*KINDS, UNPLACED)
    )
    flush_ms = {  # by part, as the flushes count them (workers.stages.register.flush)
        m.group(1): 1000 * value / max(frames_in, 1)
        for key, value in delta.items()
        if (m := re.fullmatch(r"flush_(\w+)_cpu_seconds_total", key))
    }
    flushes_ms = sum(flush_ms.values())
    tiles_ms, images_ms = flush_ms.get("tiles", 0.0) + flush_ms.get("pyramid", 0.0), flush_ms.get("images", 0.0)
    rest_ms = 1000 * (workers_cpu_s - counted) / frames_in - flushes_ms if frames_in else math.nan
    return (
        f"| {n} | {share:.1f} | {prepare_ms:.1f} | {register_ms[KEYFRAME]:.1f} | {register_ms[TRACKED]:.1f} "
        f"| {prepare_ms + register_ms[KEYFRAME]:.1f} | {prepare_ms + register_ms[TRACKED]:.1f} "
        f"| {flushes_ms:.1f} ({tiles_ms:.1f} / {images_ms:.1f}) "
        f"| {rest_ms:.1f} |"
    )


def finish_parts(counters: dict[str, float]) -> list[str]:
    """Return the finish's parts the workers count (finish_<part>_wall_seconds_total: workers.stages.register
    .completion), in the order GET /metrics gives them."""
    return [m.group(1) for key in counters if (m := re.fullmatch(r"finish_(\w+)_wall_seconds_total", key))]


def finish_line(n: int, before: dict[str, float], after: dict[str, float], parts: list[str]) -> str:
    """Return a table row: the sessions finished in a run, the mean wall seconds of their finishes by part and in
    all, the frames each pasted again, and the finish runs ahead with their CPU seconds."""
    delta = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in after}
    done = delta.get("sessions_finished_total", 0.0)
    mean = {k: delta.get(f"finish_{k}_wall_seconds_total", 0.0) / done if done else math.nan for k in parts}
    again = delta.get("finish_frames_pasted_again_total", 0.0) / done if done else math.nan
    runs = delta.get("finish_ahead_runs_total", 0.0)
    ahead_cpu = delta.get("finish_ahead_cpu_seconds_total", 0.0)
    cells = " | ".join(f"{mean[k]:.2f}" for k in parts)
    return f"| {n} | {done:.0f} | {cells} | {sum(mean.values()):.2f} | {again:.0f} | {runs:.0f} ({ahead_cpu:.1f} s) |"


class Usage:
    """CPU seconds and peak RSS of the service's processes, sampled every 0.5 s while running."""

    def __init__(self, service: Service) -> None:
        self.names = {pid: name for name, pid in service.pids().items()}  # api, worker-1, ...
        redis_pid = embedded_pid(service.embedded) if service.embedded is not None else None
        if redis_pid is not None:
            self.names[redis_pid] = "redis (embedded)"
        self.names[os.getpid()] = "bench client"  # uploads and polls; on a clinic's network it is not here
        self.procs = {pid: psutil.Process(pid) for pid in self.names}
        self.cpu0 = {pid: self._cpu(p) for pid, p in self.procs.items()}
        self.peak = dict.fromkeys(self.procs, 0.0)
        self.halt = threading.Event()
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()

    @staticmethod
    def _cpu(p: psutil.Process) -> float:
        with contextlib.suppress(psutil.Error):
            t = p.cpu_times()
            return t.user + t.system
        return 0.0

    def _sample(self) -> None:
        while not self.halt.wait(0.5):
            for pid, p in self.procs.items():
                with contextlib.suppress(psutil.Error):
                    self.peak[pid] = max(self.peak[pid], p.memory_info().rss / 2**20)

    def stop(self) -> dict[str, tuple[float, float]]:
        """Return {process name: (CPU s used since start, peak RSS MB)}."""
        self.halt.set()
        self.thread.join(2.0)
        return {self.names[pid]: (self._cpu(p) - self.cpu0[pid], self.peak[pid]) for pid, p in self.procs.items()}


def run_probes(service: Service, key: str, scans: list[tuple[Path, object]], args: argparse.Namespace) -> list[Row]:
    """Upload every scan at once into its own session; return each session's figures."""
    with ThreadPoolExecutor(max_workers=len(scans)) as pool:
        futures = [
            pool.submit(run, service, key, folder, scan, args.rate, f"probe {k + 1}/{len(scans)}", args)
            for k, (folder, scan) in enumerate(scans)
        ]
        return [f.result() for f in futures]


def main(argv: list[str] | None = None) -> int:
    """Start the service, run each number of probes, print the table; return 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--probes", default="1,3", help="numbers of simultaneous probes, the first is the baseline")
    p.add_argument("--scenario", default="raster", choices=[s for s in ALL_SCENARIOS if s != "calib"])
    p.add_argument("--frames", type=int, default=336, help="upload each scan's first N frames")
    p.add_argument(
        "--scan",
        type=Path,
        action="append",
        default=None,
        help="a scan folder (e.g. ../shared/scans/raster_veins_23) instead of the simulated scenario: probe k "
        "uploads the k-th given, cycling (repeat the option)",
    )
    p.add_argument("--rate", type=float, default=10.0, help="upload rate per probe, frames/s")
    p.add_argument("--workers", type=int, default=2, help="worker processes")
    p.add_argument("--poll", type=float, default=0.2, help="seconds between each session's state polls")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds allowed after the uploads' schedule")
    p.add_argument("--worker-config", default=None, help='VEINMOSAIC_WORKER_CONFIG, e.g. {"image_every_s": 10}')
    p.add_argument("--frames-csv", type=Path, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    counts = [int(v) for v in args.probes.split(",")]
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    key = "bench-" + secrets.token_urlsafe(24)
    redis_url = get_settings().redis_url
    prefix = f"vmbench:{secrets.token_hex(6)}:"
    env = {"VEINMOSAIC_API_KEYS": json.dumps({key: ["ingest", "view"]}), "VEINMOSAIC_LOG_LEVEL": "WARNING"}
    if redis_url:
        env["VEINMOSAIC_REDIS_PREFIX"] = prefix
    if args.worker_config:
        env["VEINMOSAIC_WORKER_CONFIG"] = args.worker_config
    results: list[tuple[int, list[Row], dict[str, tuple[float, float]]]] = []
    costs: list[str] = []
    counted: list[tuple[int, dict[str, float], dict[str, float]]] = []  # each run's counters before and after
    with tempfile.TemporaryDirectory(prefix="vm-probes-", ignore_cleanup_errors=True) as tmp:
        scans = []
        for seed in range(1, max(counts) + 1):
            if args.scan:
                scan = first_frames(read_scan_folder(args.scan[(seed - 1) % len(args.scan)]), args.frames)
            else:
                print(f"simulating {args.scenario} seed {seed} ...", file=sys.stderr)
                length = args.frames if args.scenario in LONG_SCENARIOS else None  # an exam: as long as asked
                scan = first_frames(simulate(args.scenario, seed, frames=length), args.frames)
            folder = Path(tmp) / f"scan{seed}"
            write_scan_folder(scan, folder)
            scans.append((folder, scan))
        service = Service(
            Path(tmp) / "data", port=free_port(), workers=args.workers, redis_url=redis_url, extra_env=env
        )
        try:
            service.start()
            for n in counts:
                usage, before = Usage(service), service_counters(service)
                rows = run_probes(service, key, scans[:n], args)
                use = usage.stop()
                workers_cpu_s = sum(cpu for name, (cpu, _) in use.items() if name.startswith("worker"))
                after = service_counters(service)
                costs.append(cost_line(n, before, after, workers_cpu_s, sum(r.frames for r in rows)))
                counted.append((n, before, after))
                # the accuracy reports after the run's CPU and counters are read: their work counts in neither
                rows = [with_rmse(service, key, r, folder) for r, (folder, _) in zip(rows, scans[:n], strict=True)]
                results.append((n, rows, use))
                time.sleep(2.0)  # let the workers go idle between runs
        finally:
            service.stop()
            if redis_url:
                with contextlib.closing(redis.Redis.from_url(redis_url)) as r:
                    for k in r.scan_iter(match=f"{prefix}*", count=1000):
                        r.delete(k)
    config = f", worker config {args.worker_config}" if args.worker_config else ""
    source = ", ".join(sorted({f.name for f in args.scan})) if args.scan else args.scenario
    print(f"\n{source}, {args.frames} frames per probe at {args.rate:g} f/s; {args.workers} workers{config}\n")
    head = ["probes", "session", "proc f/s", "lag p50 s", "lag p95 s", "done after last upload s", "placed %"]
    head.append("RMSE mm")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    base_rate = None
    for n, rows, _ in results:
        total = sum(r.proc_rate for r in rows if np.isfinite(r.proc_rate))
        base_rate = base_rate or total
        for k, r in enumerate(rows):
            p50, p95 = (np.percentile(r.lag, q) for q in (50, 95)) if r.lag.size else (np.nan, np.nan)
            print(
                f"| {n} | {k + 1} | {r.proc_rate:.2f} | {p50:.2f} | {p95:.2f} | {r.done_s:.1f} "
                f"| {100 * r.registered:.1f} | {r.rmse_mm:.3f} |"
            )
        print(f"| {n} | all | {total:.2f} ({total / base_rate:.2f}x) | | | | | |")
    print("\n| probes | process | CPU s/frame | peak MB |")
    print("|---|---|---|---|")
    for n, rows, use in results:
        frames = sum(r.frames for r in rows)
        for name, (cpu, peak) in sorted(use.items()):
            print(f"| {n} | {name} | {cpu / frames:.3f} | {peak:.0f} |")
        workers = sum(cpu for name, (cpu, _) in use.items() if name.startswith("worker"))
        print(f"| {n} | all workers | {workers / frames:.3f} | |")
        served = sum(cpu for name, (cpu, _) in use.items() if name != "bench client")
        print(f"| {n} | the service (API, workers, Redis) | {served / frames:.3f} | |")
    print("\nthe workers' CPU ms by frame (GET /metrics): a keyframe is described (SIFT) and matched, a tracked frame")
    print("aligned on a keyframe (`track_overlap`); registering counts the paste and refinements it brings; flushes")
    print("(tiles with the pyramid / the whole images) and the rest (the finish, settling, the queue) per frame")
    print("uploaded\n")
    head = ["probes", "keyframes %", "prepare", "register: keyframe", "tracked", "all: keyframe", "tracked"]
    head += ["flushes (tiles / images)", "the rest"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    print("\n".join(costs))
    print("\neach session's finish from its last frame registered (GET /metrics, wall s, the mean over the sessions):")
    print("final refinement, calibration, restitch, final flush; frames pasted again; finish runs ahead (their CPU)\n")
    parts = finish_parts(counted[-1][2])
    head = ["probes", "sessions", *parts, "in all", "pasted again", "runs ahead (CPU)"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    print("\n".join(finish_line(n, before, after, parts) for n, before, after in counted))
    last = results[-1][1]
    done_ok = all(r.done_s <= DONE_TARGET_S for r in last)
    lag_ok = all(r.lag.size and np.percentile(r.lag, 95) <= LAG_P95_TARGET_S for r in last)
    print(f"\n{results[-1][0]} probes: every session done within {DONE_TARGET_S:g} s: {'yes' if done_ok else 'no'}; ")
    print(f"lag p95 <= {LAG_P95_TARGET_S:g} s: {'yes' if lag_ok else 'no'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
