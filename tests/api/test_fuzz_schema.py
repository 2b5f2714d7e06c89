"""Schemathesis 4 over /openapi.json of a real API process (issue 8): every check, bounded examples.

No 5xx, no status the schema does not state, no schema-valid request rejected, no schema-violating request
accepted, no route answering without its credential (the schema declares them: a bearer key, or a viewer
token on a session's GET routes). The key is made for this run. Two operations take content that JSON Schema
cannot describe, so there a 415/422 for valid-by-schema data is expected: a frame's `image` must be a
decodable grayscale PNG/TIFF/JPEG of the session's calibrated size, and reference.csv must name the
session's frames. Bounded by examples, not by time (one worker, MAX_EXAMPLES per operation, each phase once:
about 2,500 cases in ~20 s on two cores). `--max-time` is not passed: it is a budget that fuzzing and
stateful testing repeat to fill, so a 110 s value made this one test take two minutes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
from live_server import live_api

MAX_EXAMPLES = 25
TIMEOUT_S = 300  # a hang, not a budget: the run ends when its phases do
CONTENT_CHECKED = ("/v1/sessions/{session_id}/frames", "/v1/sessions/{session_id}/reference")
CONFIG = """
[checks.positive_data_acceptance]
expected-statuses = ["2xx", "3xx", "401", "403", "404", "409", "429", "5xx"]
""" + "".join(
    f"""
[[operations]]
include-path = "{path}"
include-method = "POST"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "403", "404", "409", "415", "422", "5xx"]
"""
    for path in CONTENT_CHECKED
)


@pytest.mark.slow
def test_schemathesis_finds_nothing(tmp_path: Path) -> None:
    key = f"fuzz-{uuid.uuid4().hex}"
    config = tmp_path / "schemathesis.toml"
    config.write_text(CONFIG)
    with live_api(tmp_path, {key: ["ingest", "view", "admin"]}, log_level="WARNING") as api:
        st = Path(sys.executable).with_name("st")
        command = [
            str(st), "--config-file", str(config), "run", f"{api.base_url}/openapi.json",
            "-H", f"Authorization: Bearer {key}", "--checks", "all", "-n", str(MAX_EXAMPLES),
            "--seed", "8", "-w", "1", "--request-timeout", "10",
        ]  # fmt: skip
        env = {**os.environ, "SCHEMATHESIS_HOOKS": ""}
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=TIMEOUT_S)
        server_errors = [line for line in api.log_lines() if '"status": 500' in line or "Traceback" in line]
    report = done.stdout[-6000:] + done.stderr[-2000:]
    assert server_errors == [], server_errors[:5]
    assert done.returncode == 0, report
    assert "Tested:" in done.stdout, report
    print(done.stdout[-1500:])  # the summary, shown with -s
