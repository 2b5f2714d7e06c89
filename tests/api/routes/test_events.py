"""Server-Sent Events: snapshot first, progress from the Redis stream, Last-Event-ID resume, keep-alive, done."""

from __future__ import annotations

import json
import threading
from typing import Any

import pytest
from api_helpers import INGEST, auth, calibration_doc
from fastapi.testclient import TestClient

from api.routes import events as events_module
from services.jobs import queue


def parse_sse(text: str) -> tuple[list[dict[str, Any]], list[str]]:
    """Return (events [{"id", "event", "data"}], comment lines) of an SSE body."""
    events: list[dict[str, Any]] = []
    comments: list[str] = []
    current: dict[str, Any] = {}
    data: list[str] = []
    for line in text.split("\n"):
        if line == "":
            if data or "event" in current:
                events.append({**current, "data": json.loads("\n".join(data)) if data else None})
            current, data = {}, []
        elif line.startswith(":"):
            comments.append(line[1:].strip())
        else:
            field, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if field == "data":
                data.append(value)
            elif field in ("id", "event"):
                current[field] = value
    return events, comments


def publish(client: TestClient, sid: str, kind: str, **data: Any) -> str:
    """XADD an event the way the workers do; return its stream id."""
    r = client.app.state.redis  # type: ignore[attr-defined]
    prefix = client.app.state.settings.redis_prefix  # type: ignore[attr-defined]
    entry = r.xadd(queue.events_stream(sid, prefix), {"type": kind, "data": json.dumps(data)})
    return entry.decode() if isinstance(entry, bytes) else entry


def stream(client: TestClient, sid: str, **headers: str) -> tuple[list[dict[str, Any]], list[str], Any]:
    """GET the event stream to its end; return (events, comments, response)."""
    resp = client.get(f"/v1/sessions/{sid}/events", headers={**INGEST, **headers})
    assert resp.status_code == 200, resp.text
    assert resp.headers["content-type"].startswith("text/event-stream")
    assert resp.headers["cache-control"] == "private, no-store"  # the stream carries the path
    events, comments = parse_sse(resp.text)
    return events, comments, resp


@pytest.fixture
def fast_keepalive(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the keep-alive interval (and so the XREAD BLOCK) 50 ms."""
    monkeypatch.setattr(events_module, "KEEPALIVE_S", 0.05)


def test_fresh_connection_gets_snapshot_then_done(client: TestClient, session_id: str) -> None:
    publish(client, session_id, "progress", processed=1)
    publish(client, session_id, "progress", processed=2)
    done_id = publish(client, session_id, "done", processed=2, status="done")
    events, _, resp = stream(client, session_id)
    assert resp.text.startswith("retry: ")
    assert [e["event"] for e in events] == ["snapshot", "done"]  # the snapshot replaces older progress
    snap = events[0]
    assert snap["id"] == done_id and snap["data"]["session"] == session_id
    assert snap["data"]["mosaic"] is None and snap["data"]["path"] == [] and snap["data"]["status"] == "receiving"
    assert "label" not in json.dumps(snap["data"])  # no patient label in the event stream
    assert events[1]["id"] == done_id and events[1]["data"]["processed"] == 2


def test_resume_with_last_event_id(client: TestClient, session_id: str) -> None:
    ids = [publish(client, session_id, "progress", processed=i) for i in range(1, 4)]
    done_id = publish(client, session_id, "done", processed=3)
    events, _, _ = stream(client, session_id, **{"Last-Event-ID": ids[0]})
    assert [(e["event"], e["id"]) for e in events] == [
        ("progress", ids[1]),
        ("progress", ids[2]),
        ("done", done_id),
    ]
    assert [e["data"]["processed"] for e in events] == [2, 3, 3]
    # the same through the query string (for clients that cannot set the header)
    resp = client.get(f"/v1/sessions/{session_id}/events?last_event_id={ids[1]}", headers=INGEST)
    assert [e["id"] for e in parse_sse(resp.text)[0]] == [ids[2], done_id]


def test_trimmed_resume_falls_back_to_snapshot(client: TestClient, session_id: str) -> None:
    publish(client, session_id, "progress", processed=1)
    done_id = publish(client, session_id, "done", processed=1)
    events, _, _ = stream(client, session_id, **{"Last-Event-ID": "1-0"})  # older than anything retained
    assert [e["event"] for e in events] == ["snapshot", "done"] and events[1]["id"] == done_id
    garbage, _, _ = stream(client, session_id, **{"Last-Event-ID": "not-an-id"})  # ignored: fresh start
    assert garbage[0]["event"] == "snapshot"


def test_live_events_and_keepalive(client: TestClient, session_id: str, fast_keepalive: None) -> None:
    first = publish(client, session_id, "progress", processed=1, tiles={"vein": {"12/3_4": 1}})
    timers = [
        threading.Timer(0.4, publish, (client, session_id, "progress"), {"processed": 2}),
        threading.Timer(0.8, publish, (client, session_id, "done"), {"processed": 2, "status": "done"}),
    ]
    for t in timers:
        t.start()
    try:
        events, comments, _ = stream(client, session_id)
    finally:
        for t in timers:
            t.join()
    assert [e["event"] for e in events] == ["snapshot", "progress", "done"]
    assert events[0]["id"] == first and events[1]["data"]["processed"] == 2
    assert "keep-alive" in comments  # idle periods between the events are filled with comments


def test_finished_session_ends_after_snapshot(client: TestClient, session_id: str) -> None:
    client.app.state.store.set_status(session_id, "done")  # type: ignore[attr-defined]
    events, _, _ = stream(client, session_id)
    assert [e["event"] for e in events] == ["snapshot", "done"]
    assert events[0]["data"]["status"] == "done" and events[1]["data"]["status"] == "done"


def test_events_auth(client: TestClient, session_id: str) -> None:
    publish(client, session_id, "done", processed=0)
    url = f"/v1/sessions/{session_id}/events"
    assert client.get(url).status_code == 401
    assert client.get(url, headers=auth("ingest-key-b")).status_code == 404
    other = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=auth("ingest-key-b")).json()
    assert client.get(f"{url}?token={other['viewer_token']}").status_code == 401
    token = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    assert client.get(f"/v1/sessions/{token['id']}/events?token={other['viewer_token']}").status_code == 401
    state = client.get(f"/v1/sessions/{session_id}", headers=INGEST).json()
    assert state["id"] == session_id
    resp = client.get(url, headers=auth("admin-key"))
    assert resp.status_code == 200 and parse_sse(resp.text)[0][-1]["event"] == "done"


def test_viewer_token_reads_events(client: TestClient) -> None:
    created = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    publish(client, created["id"], "done", processed=0)
    resp = client.get(f"/v1/sessions/{created['id']}/events?token={created['viewer_token']}")
    assert resp.status_code == 200 and [e["event"] for e in parse_sse(resp.text)[0]] == ["snapshot", "done"]
