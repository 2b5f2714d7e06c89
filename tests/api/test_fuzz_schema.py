"""Schemathesis 4 over /openapi.json of a real API process (issue 8): every check, bounded examples.

No 5xx, no status the schema does not state, no schema-valid request rejected, no schema-violating request
accepted, no route answering without its credential (the schema declares them: a bearer key, or a viewer
token on a session's GET routes). The key is made for this run. Two operations take content that JSON Schema
cannot describe, so there a 415/422 for valid-by-schema data is expected: a frame's `image` must be a
decodable grayscale PNG/TIFF/JPEG of the session's calibrated size, and reference.csv must name the
session's frames. Bounded by examples, not by time (one worker, MAX_EXAMPLES per operation and
STATEFUL_EXAMPLES scenarios, each phase once: about 4,000 cases in ~25 s on two cores). `--max-time` is not
passed: it is a budget that fuzzing and stateful testing repeat to fill, so a 110 s value made this one test
take two minutes.

The fuzzing reaches the core (issue 16): the stateful phase follows the schema's OpenAPI links
(api/openapi_links.py) from POST /v1/sessions into the operations that take its `session_id`, so it uploads
forces into sessions it created, finishes them and reads them. Schemathesis's own link inference is off, so
this measures the links the schema documents: without them there is no stateful phase and the test fails.
Its calls are valid by the schema (the coverage and fuzzing phases send the invalid ones), and no example
database is replayed, so a run depends on the seed and the schema only. An event stream is read up to its
first event (the snapshot): an open session's stream never ends, and each read would last the request timeout.
"""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import httpx
import pytest
from live_server import live_api

MAX_EXAMPLES = 25
STATEFUL_EXAMPLES = 150  # scenarios of up to STATEFUL_STEPS calls each; ~10 s
STATEFUL_STEPS = 10
TIMEOUT_S = 300  # a hang, not a budget: the run ends when its phases do
CONTENT_CHECKED = ("/v1/sessions/{session_id}/frames", "/v1/sessions/{session_id}/reference")
CONFIG = f"""
max-stream-events = 1

[generation]
database = "none"

[phases.stateful]
max-steps = {STATEFUL_STEPS}

[phases.stateful.generation]
max-examples = {STATEFUL_EXAMPLES}
mode = "positive"

[phases.stateful.inference]
algorithms = []

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
# What the stateful phase must show. Seed 8 measured 637 linked calls over 18 of 18 session operations, none
# answered "no such session", 20 force batches and 70 finishes answered 202, 25 frames refused by the image
# checks (415/422: random bytes are no frame of the session's size); seeds 4-7: 559-742 calls, 5-20 forces.
# The bounds leave room for other seeds (a schema change reshuffles what a seed generates).
MIN_LINKED_CALLS = 100
MIN_OPERATIONS_REACHED = 0.75  # of the operations taking a session_id
MAX_UNKNOWN_SESSION = 0.02  # linked calls answered 404 "no such session"
SESSION_PREFIX = "/v1/sessions/{session_id}"


def linked_session_calls(ndjson: Path) -> list[tuple[str, int | None, bytes]]:
    """Return (operation, status, body) of each stateful call into a session whose id an OpenAPI link supplied."""
    calls = []
    for line in ndjson.read_text().splitlines():
        event: dict[str, Any] = json.loads(line)
        finished = event.get("ScenarioFinished")
        if finished is None or finished["phase"] != "stateful":
            continue
        recorder = finished["recorder"]
        for case_id, interaction in recorder.get("interactions", {}).items():
            case = recorder["cases"].get(case_id, {})
            value = case.get("value", {})
            if not case.get("is_transition_applied") or "{session_id}" not in value.get("path", ""):
                continue
            response = interaction.get("response") or {}
            body = base64.b64decode((response.get("content") or {}).get("$base64", ""))
            calls.append((f"{value['method']} {value['path']}", response.get("status_code"), body))
    return calls


@pytest.mark.slow
def test_schemathesis_finds_nothing(tmp_path: Path) -> None:
    key = f"fuzz-{uuid.uuid4().hex}"
    config = tmp_path / "schemathesis.toml"
    config.write_text(CONFIG)
    reports = tmp_path / "reports"
    # the fuzzer creates hundreds of sessions with its one key: the per-key quotas (their own tests in
    # tests/api/routes/test_sessions.py and test_ingest.py) would answer it 429 and hide the routes behind
    quotas_off = {"quota_sessions_per_key": "0", "quota_frames_per_key": "0"}
    with live_api(tmp_path, {key: ["ingest", "view", "admin"]}, log_level="WARNING", **quotas_off) as api:
        st = Path(sys.executable).with_name("st")
        command = [
            str(st), "--config-file", str(config), "run", f"{api.base_url}/openapi.json",
            "-H", f"Authorization: Bearer {key}", "--checks", "all", "-n", str(MAX_EXAMPLES),
            "--seed", "8", "-w", "1", "--request-timeout", "10",
            "--report", "ndjson", "--report-dir", str(reports),
        ]  # fmt: skip
        env = {**os.environ, "SCHEMATHESIS_HOOKS": ""}
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=TIMEOUT_S)
        server_errors = [line for line in api.log_lines() if '"status": 500' in line or "Traceback" in line]
        schema = httpx.get(f"{api.base_url}/openapi.json", headers={"Authorization": f"Bearer {key}"}).json()
    session_operations = {
        f"{method.upper()} {path}"
        for path, item in schema["paths"].items()
        for method, operation in item.items()
        if any(p["in"] == "path" and p["name"] == "session_id" for p in operation.get("parameters", []))
    }
    report = done.stdout[-6000:] + done.stderr[-2000:]
    assert server_errors == [], server_errors[:5]
    assert done.returncode == 0, report
    assert "Tested:" in done.stdout, report
    print(done.stdout[-1500:])  # the summary, shown with -s

    calls = linked_session_calls(next(reports.glob("*.ndjson")))
    answered = Counter((operation, status) for operation, status, _ in calls)
    unknown = sum(1 for _, status, body in calls if status == 404 and b"no such session" in body)
    reached = {operation for operation, _, _ in calls}
    print(f"stateful: {len(calls)} linked calls over {len(reached)}/{len(session_operations)} session operations")
    assert len(calls) >= MIN_LINKED_CALLS, (len(calls), report)
    assert len(reached) >= MIN_OPERATIONS_REACHED * len(session_operations), sorted(session_operations - reached)
    assert unknown <= MAX_UNKNOWN_SESSION * len(calls), (unknown, len(calls))
    assert answered[(f"POST {SESSION_PREFIX}/forces", 202)] >= 1, answered  # forces stored in a fuzzer's session
    assert answered[(f"POST {SESSION_PREFIX}/finish", 202)] >= 1, answered
    frames = f"POST {SESSION_PREFIX}/frames"
    assert answered[(frames, 415)] + answered[(frames, 422)] >= 1, answered  # past the session, into the image checks
