"""Process-wide defaults `services` sets before numpy and OpenCV load (services/__init__.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# every BLAS library the process has loaded, with the threads it will use (threadpoolctl reads them from the library)
BLAS_THREADS = "import json, threadpoolctl as t; print(json.dumps([i['num_threads'] for i in t.threadpool_info()]))"


def _probe(code: str, env_value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if env_value is not None:
        env["OPENBLAS_NUM_THREADS"] = env_value
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_one_blas_thread_per_process_unless_the_operator_says_otherwise() -> None:
    probe = "import services, numpy, os; print(os.environ['OPENBLAS_NUM_THREADS'])"
    assert _probe(probe, None) == "1"  # busy-waiting BLAS threads took the CPU from other workers
    assert _probe(probe, "3") == "3"


def test_blas_loaded_before_services_is_limited_too() -> None:
    # cv2 loads numpy and its BLAS before `python -m workers.main` reaches services (docker-compose starts the
    # workers so): the variable comes too late there, the loaded libraries must be limited at run time
    before = json.loads(_probe(f"import cv2; {BLAS_THREADS}", None))
    # loaded with a thread per core: what the package must change
    assert before and (max(before) > 1 or os.cpu_count() == 1)
    assert set(json.loads(_probe(f"import cv2, services; {BLAS_THREADS}", None))) == {1}
    assert set(json.loads(_probe(f"import workers.main; {BLAS_THREADS}", None))) == {1}
    assert set(json.loads(_probe(f"import numpy, services; {BLAS_THREADS}", "2"))) == {2}  # the operator's value
