"""The real service the headless-Chromium viewer tests run against, and where Chromium and its flags are.

Redis is the server at REDIS_URL (private key prefix) when set, else the embedded one; the API on a free port
with one key (ingest + view) and `workers` worker processes (0: the test writes results itself).
"""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from live_server import free_port

from cli.launcher import Service

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"


@contextmanager
def browser_service(
    data_dir: Path, key: str, workers: int, worker_config: dict[str, Any] | None = None
) -> Iterator[Service]:
    """Start the service for a browser test (fails the test when Chromium is missing) and stop it afterwards."""
    if not os.path.exists(CHROMIUM):
        pytest.fail(f"{CHROMIUM} is missing: install Debian's chromium (scripts/test.sh does)")
    extra_env = {
        "VEINMOSAIC_API_KEYS": json.dumps({key: ["ingest", "view"]}),
        "VEINMOSAIC_REDIS_PREFIX": f"vmbrowser:{uuid.uuid4().hex}:",
        "VEINMOSAIC_TOKEN_SECRET": f"browser-{uuid.uuid4().hex}",
        "VEINMOSAIC_LOG_LEVEL": "WARNING",
    }
    if worker_config:
        extra_env["VEINMOSAIC_WORKER_CONFIG"] = json.dumps(worker_config)
    svc = Service(
        data_dir,
        port=free_port(),
        workers=workers,
        redis_url=os.environ.get("REDIS_URL") or None,
        extra_env=extra_env,
    )
    with svc:
        yield svc
