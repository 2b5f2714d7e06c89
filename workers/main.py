"""The worker process: settings and command line, then one loop over the job streams (workers.jobs.loop.Worker).

SIGTERM or SIGINT stops the loop after the current entry; held sessions are flushed and handed off. What the
loop does with each entry (read, dispatch, run a job, dead-letter): the workers.jobs package.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2

from services.core.inputs.image_header import DEFAULT_MAX_FRAME_SIDE
from services.decoder_limits import set_decoder_limits
from services.jobs.redis_backend import close, connect
from services.pacs.destinations import without_tls
from services.settings import Settings
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore
from workers.config import Context, WorkerConfig
from workers.jobs.loop import Worker

__all__ = ["Worker", "build_parser", "main", "run_worker", "worker_config"]


def run_worker(
    data_dir: Path | str,
    redis_url: str | None = None,
    *,
    prefix: str = "vm:",
    consumer: str | None = None,
    stop: threading.Event | None = None,
    max_seconds: float | None = None,
    handle_signals: bool = True,
    max_frame_side: int = DEFAULT_MAX_FRAME_SIDE,
    config: WorkerConfig | None = None,
    **options: Any,
) -> int:
    """Return the exit code 0 after running one worker until SIGTERM/SIGINT (or `stop` is set, or max_seconds pass).

    config: the worker's configuration made from the settings (WorkerConfig.from_settings, what main() passes);
    without it one is made from data_dir, redis_url, prefix, consumer and `options`, any other WorkerSettings
    field (lost_timeout_s, lease_ms, flush_every_s, debug_order, ...; an unknown field is refused).

    max_frame_side (the settings' frame size cap) sets Pillow's pixel limit in this process and makes the
    store refuse a larger frame from its header, before any decode (OpenCV's cap is set by `services`).
    """
    if config is None:
        cfg_args: dict[str, Any] = {"data_dir": Path(data_dir), "redis_url": redis_url, "prefix": prefix, **options}
        if consumer:
            cfg_args["consumer"] = consumer
        config = WorkerConfig.model_validate(cfg_args)
    cfg = config
    set_decoder_limits(max_frame_side)
    r = connect(cfg.redis_url, cfg.data_dir)
    store = SessionStore(cfg.data_dir, max_frame_side=max_frame_side)
    ctx = Context(cfg, r, store, ResultsStore(cfg.data_dir), stop or threading.Event())
    if handle_signals and threading.current_thread() is threading.main_thread():

        def on_signal(_signum: int, _frame: object) -> None:
            ctx.stop.set()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
    try:
        Worker(ctx).run(max_seconds=max_seconds)
    finally:
        close(r)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Return the worker's argument parser; what it leaves out comes from services.settings.Settings."""
    p = argparse.ArgumentParser(prog="veinmosaic worker", description="Run one veinmosaic worker process.")
    p.add_argument("--data-dir", type=Path, default=None, help="default: VEINMOSAIC_DATA_DIR")
    p.add_argument("--redis-url", default=None, help="default: REDIS_URL (else the embedded server)")
    p.add_argument("--prefix", default=None, help="Redis key prefix; default VEINMOSAIC_REDIS_PREFIX or vm:")
    p.add_argument("--consumer", default=None, help="consumer name; default host:pid")
    p.add_argument(
        "--config-json",
        default=None,
        help='JSON of WorkerSettings fields, e.g. {"lost_timeout_s": 5}, over VEINMOSAIC_WORKER_CONFIG\'s',
    )
    p.add_argument("--lost-timeout-s", type=float, default=None, help="default: from the settings' worker_config")
    p.add_argument("--lease-ms", type=int, default=None, help="default: from the settings' worker_config")
    p.add_argument("--claim-idle-ms", type=int, default=None, help="default: from the settings' worker_config")
    p.add_argument("--max-seconds", type=float, default=None, help="exit after this long (tests)")
    p.add_argument("--heartbeat-file", default=None, help="touched every loop (at most every 2 s), for health checks")
    return p


def worker_config(args: argparse.Namespace, settings: Settings) -> WorkerConfig:
    """Return the worker's configuration: the settings, then --config-json's fields, then the single options."""
    overrides: dict[str, Any] = json.loads(args.config_json) if args.config_json else {}
    if not isinstance(overrides, dict):
        raise ValueError("--config-json: expected a JSON object of WorkerSettings fields")
    for name in ("lost_timeout_s", "lease_ms", "claim_idle_ms", "heartbeat_file"):
        if getattr(args, name) is not None:  # an option left out keeps --config-json's value
            overrides[name] = getattr(args, name)
    for name in ("data_dir", "redis_url", "prefix", "consumer"):
        if getattr(args, name) is not None:
            overrides[name] = getattr(args, name)
    return WorkerConfig.from_settings(settings, **overrides)


def main(argv: Sequence[str] | None = None) -> int:
    """Return the exit code of a worker run as services.settings.Settings (read once, here) and the command line say."""
    from services.log_format import configure_json_logging

    args = build_parser().parse_args(argv)
    settings = Settings()
    configure_json_logging(str(settings.log_level))
    if settings.worker_nice:
        with contextlib.suppress(OSError):
            os.nice(settings.worker_nice)  # ingest (API) before processing when the CPU is short
    cv2.setNumThreads(settings.worker_cv_threads)
    for line in without_tls(settings.pacs_destinations):
        logging.getLogger("veinmosaic.worker").warning(line)
    config = worker_config(args, settings)
    return run_worker(
        config.data_dir,
        config.redis_url,
        max_seconds=args.max_seconds,
        max_frame_side=settings.max_frame_side,
        config=config,
    )


if __name__ == "__main__":
    raise SystemExit(main())
