"""Process-wide defaults `services` sets before numpy and OpenCV load (services/__init__.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PROBE = "import services, numpy, os; print(os.environ['OPENBLAS_NUM_THREADS'])"


def _blas_threads(env_value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if env_value is not None:
        env["OPENBLAS_NUM_THREADS"] = env_value
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_one_blas_thread_per_process_unless_the_operator_says_otherwise() -> None:
    assert _blas_threads(None) == "1"  # busy-waiting BLAS threads took the CPU from other workers
    assert _blas_threads("3") == "3"
