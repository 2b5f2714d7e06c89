"""GET /metrics: Prometheus text format 0.0.4 that parses, with counters from Redis and queue gauges."""

from __future__ import annotations

import re

import pytest
import redis
from api_helpers import INGEST, frame_bytes, upload
from fastapi.testclient import TestClient

from services.jobs import queue

SAMPLE = re.compile(
    r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{[a-zA-Z_][a-zA-Z0-9_]*=\"[^\"]*\"(,[a-zA-Z_][a-zA-Z0-9_]*=\"[^\"]*\")*\})? (\S+)$"
)
NUMBER = re.compile(r"^(-?[0-9]+(\.[0-9]+)?([eE][-+]?[0-9]+)?|NaN|[+-]Inf)$")


def parse_exposition(text: str) -> tuple[dict[str, float], dict[str, str]]:
    """Return ({"name{labels}": value}, {family: type}); assert every line is well formed (format 0.0.4)."""
    samples: dict[str, float] = {}
    types: dict[str, str] = {}
    helped: set[str] = set()
    assert text.endswith("\n")
    for line in text.splitlines():
        if line.startswith("# HELP "):
            helped.add(line.split()[2])
            continue
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split()
            assert kind in ("counter", "gauge", "summary", "histogram", "untyped")
            assert name in helped and name not in types, name  # HELP first, one TYPE per family
            types[name] = kind
            continue
        assert not line.startswith("#") and line.strip(), line
        m = SAMPLE.match(line)
        assert m, f"malformed sample line: {line!r}"
        assert NUMBER.match(m.group(4)), line
        family = re.sub(r"_(sum|count)$", "", m.group(1)) if m.group(1) not in types else m.group(1)
        assert family in types, f"sample before its TYPE: {line!r}"
        samples[m.group(1) + (m.group(2) or "")] = float(m.group(4))
    return samples, types


def test_metrics_exposition_parses_and_counts(client: TestClient, session_id: str) -> None:
    r, prefix = client.app.state.redis, client.app.state.settings.redis_prefix  # type: ignore[attr-defined]
    queue.incr_metric(r, "frames_processed_total", 7, prefix=prefix)
    queue.incr_metric(r, "job_seconds_sum", 2.5, prefix=prefix)
    queue.incr_metric(r, "job_seconds_count", 1, prefix=prefix)
    queue.incr_metric(r, "prepare_retries_total", 3, prefix=prefix)  # a metric the API does not know yet
    assert upload(client, session_id, 0, frame_bytes(0)).status_code == 202  # one job on the frame queue
    client.get(f"/v1/sessions/{session_id}/mosaic_files/0/0_0.png", headers=INGEST)  # a tile request (404 here)

    resp = client.get("/metrics")
    assert resp.status_code == 200
    assert resp.headers["content-type"] == "text/plain; version=0.0.4; charset=utf-8"
    samples, types = parse_exposition(resp.text)
    assert samples["veinmosaic_frames_processed_total"] == 7 and types["veinmosaic_frames_processed_total"] == "counter"
    assert samples["veinmosaic_job_seconds_sum"] == 2.5 and samples["veinmosaic_job_seconds_count"] == 1
    assert types["veinmosaic_job_seconds"] == "summary"
    assert samples["veinmosaic_prepare_retries_total"] == 3
    assert samples['veinmosaic_queue_depth{stream="frames"}'] == 1 and types["veinmosaic_queue_depth"] == "gauge"
    assert samples["veinmosaic_tile_hits_total"] == 1
    assert samples["veinmosaic_uploads_total"] == 1 and samples["veinmosaic_redis_up"] == 1
    assert session_id not in resp.text  # no session ids (nor anything else about patients) in labels


def test_metrics_when_redis_is_down(client: TestClient, monkeypatch: pytest.MonkeyPatch) -> None:
    def down(*args: object, **kwargs: object) -> None:
        raise redis.ConnectionError("down")

    monkeypatch.setattr(client.app.state.redis, "hgetall", down)  # type: ignore[attr-defined]
    resp = client.get("/metrics")
    assert resp.status_code == 200  # the scrape succeeds and says Redis is down
    samples, _ = parse_exposition(resp.text)
    assert samples["veinmosaic_redis_up"] == 0


def test_metrics_openmetrics_on_request(client: TestClient) -> None:
    """A scraper that asks for OpenMetrics gets it (prometheus_client's content negotiation), with the same values."""
    r, prefix = client.app.state.redis, client.app.state.settings.redis_prefix  # type: ignore[attr-defined]
    queue.incr_metric(r, "jobs_done_total", 2, prefix=prefix)
    resp = client.get("/metrics", headers={"Accept": "application/openmetrics-text; version=1.0.0"})
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("application/openmetrics-text")
    lines = resp.text.splitlines()
    assert lines[-1] == "# EOF" and "# TYPE veinmosaic_jobs_done counter" in lines
    assert any(line.startswith("veinmosaic_jobs_done_total ") and float(line.split()[1]) >= 2 for line in lines)
    assert 'veinmosaic_queue_depth{stream="frames"} ' in resp.text


def test_live_lag_in_the_session_state_and_metrics(client: TestClient, session_id: str) -> None:
    """Issue 15: a session's upload-to-placement lag (p50/p95 of its newest placements) in its state, the
    'falling_behind' warning past 5 s (p95), and one summary over live sessions in /metrics (no session label)."""
    r, prefix = client.app.state.redis, client.app.state.settings.redis_prefix  # type: ignore[attr-defined]
    assert client.get(f"/v1/sessions/{session_id}", headers=INGEST).json()["lag"] is None  # nothing placed yet
    queue.record_lags(r, session_id, [0.4] * 18 + [0.9, 1.1], prefix)
    state = client.get(f"/v1/sessions/{session_id}", headers=INGEST).json()
    assert state["lag"] == {"p50_s": 0.4, "p95_s": 0.91, "frames": 20}  # linear: 0.9 + 0.05 x 0.2
    assert "falling_behind" not in [w["code"] for w in state["warnings"]]
    samples, _ = parse_exposition(client.get("/metrics").text)
    assert samples['veinmosaic_live_lag_seconds{quantile="0.5"}'] == 0.4
    assert samples["veinmosaic_live_sessions"] == 1 and samples["veinmosaic_live_sessions_behind"] == 0
    queue.record_lags(r, session_id, [7.0] * 20, prefix)  # the newest placements trail by 7 s
    state = client.get(f"/v1/sessions/{session_id}", headers=INGEST).json()
    assert state["lag"]["p95_s"] == 7.0
    assert "falling_behind" in [w["code"] for w in state["warnings"]]
    text = client.get("/metrics").text
    assert parse_exposition(text)[0]["veinmosaic_live_sessions_behind"] == 1
    assert session_id not in text
