"""Server-Sent Events: snapshot first, progress from the Redis stream, Last-Event-ID resume, keep-alive, done;
open streams capped per caller (429) and in all (503)."""

from __future__ import annotations

import asyncio
import json
import os
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis
from api_helpers import INGEST, KEYS, auth, calibration_doc
from fastapi.testclient import TestClient
from live_server import live_api

from api.routes import events as events_module
from services.jobs import queue
from services.settings import Settings


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
    """Make the keep-alive interval (and so the XREAD BLOCK) 200 ms. sse_starlette pings on its own task, which at
    50 ms could fire before the response had started on a loaded machine (a CI run beside benches: the test
    client's 'body without start'); 200 ms still puts keep-alives between events 0.6 s apart."""
    monkeypatch.setattr(events_module, "KEEPALIVE_S", 0.2)


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
        threading.Timer(0.6, publish, (client, session_id, "progress"), {"processed": 2}),
        threading.Timer(1.2, publish, (client, session_id, "done"), {"processed": 2, "status": "done"}),
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
    assert client.get(url, headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404
    other = client.post(
        "/v1/sessions", json={"calibration": calibration_doc()}, headers=auth("ingest-key-b-0123456789abcdef")
    ).json()
    assert client.get(f"{url}?token={other['viewer_token']}").status_code == 401
    token = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    assert client.get(f"/v1/sessions/{token['id']}/events?token={other['viewer_token']}").status_code == 401
    state = client.get(f"/v1/sessions/{session_id}", headers=INGEST).json()
    assert state["id"] == session_id
    resp = client.get(url, headers=auth("admin-key-0123456789abcdef"))
    assert resp.status_code == 200 and parse_sse(resp.text)[0][-1]["event"] == "done"


def test_viewer_token_reads_events(client: TestClient) -> None:
    created = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    publish(client, created["id"], "done", processed=0)
    resp = client.get(f"/v1/sessions/{created['id']}/events?token={created['viewer_token']}")
    assert resp.status_code == 200 and [e["event"] for e in parse_sse(resp.text)[0]] == ["snapshot", "done"]


# ----- the cap on open streams (api/limits.py StreamSlots) ----------------------------------------------------------


def test_event_streams_are_capped_per_caller_and_in_all(make_client: Any) -> None:
    client = make_client(events_max_per_principal=2, events_max_total=3, retry_after_s=4)
    created = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    sid, token = created["id"], created["viewer_token"]
    slots = client.app.state.stream_slots  # type: ignore[attr-defined]
    slots.open[f"token:{sid}"] = 2  # two streams of this session's viewer links are open
    over = client.get(f"/v1/sessions/{sid}/events?token={token}")
    assert over.status_code == 429 and over.headers["Retry-After"] == "4"
    assert over.json()["error"]["code"] == "rate_limited"
    slots.open["key:someone-else"] = 1  # three in all: the total cap
    full = client.get(f"/v1/sessions/{sid}/events", headers=INGEST)
    assert full.status_code == 503 and full.headers["Retry-After"] == "4"
    assert full.json()["error"]["code"] == "too_many_streams"
    slots.open.clear()
    publish(client, sid, "done", processed=0)
    assert client.get(f"/v1/sessions/{sid}/events?token={token}").status_code == 200
    assert slots.total == 0 and slots.open == {}  # the slot is freed when the stream ends


async def _open_streams(base: str, url: str, n: int, hold_s: float) -> tuple[list[int], list[float]]:
    """Open n event streams at once, hold the accepted ones open; return the statuses and /readyz latencies (s)."""
    statuses: list[int] = []
    latencies: list[float] = []
    limits = httpx.Limits(max_connections=n + 10, max_keepalive_connections=0)
    async with httpx.AsyncClient(base_url=base, timeout=30, limits=limits) as http:
        answered = asyncio.Event()

        async def one() -> None:
            async with http.stream("GET", url) as resp:
                statuses.append(resp.status_code)
                if len(statuses) == n:
                    answered.set()
                if resp.status_code == 200:
                    await asyncio.sleep(hold_s)  # held open while /readyz is probed

        async def probe() -> None:
            await answered.wait()
            for _ in range(5):
                t0 = time.perf_counter()
                ready = await http.get("/readyz")
                latencies.append(time.perf_counter() - t0)
                assert ready.status_code == 200
                await asyncio.sleep(0.1)

        await asyncio.gather(*(one() for _ in range(n)), probe())
    return statuses, latencies


@pytest.mark.slow
def test_200_streams_on_one_token_are_capped_while_readyz_answers(tmp_path: Path) -> None:
    with live_api(tmp_path, KEYS, log_level="WARNING") as api:
        http = httpx.Client(base_url=api.base_url, timeout=10)
        created = http.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
        url = f"/v1/sessions/{created['id']}/events?token={created['viewer_token']}"
        statuses, latencies = asyncio.run(_open_streams(api.base_url, url, 200, hold_s=3.0))
        cap = Settings().events_max_per_principal
        assert statuses.count(200) == cap and statuses.count(429) == 200 - cap, sorted(set(statuses))
        assert max(latencies) < 1.0, latencies
        assert http.get(url.replace("/events", ""), timeout=5).status_code == 200  # the link still works


# ----- shared Redis connections (api/event_hub.py) ------------------------------------------------------------------


def _api_clients(probe: Any, db: int) -> int:
    """Return how many connections the Redis server has open on database `db` (the API's; the probe's one too)."""
    return sum(1 for c in probe.client_list() if int(c.get("db", -1)) == db)


async def _streams_share_connections(
    base: str, urls: list[str], probe: Any, db: int, publish_to: Any
) -> tuple[int, int, list[list[str]]]:
    """Open the streams one after another (each up to its snapshot); return the server's connections before and
    with all open, and the events each stream got once a progress then a done event were published."""
    limits = httpx.Limits(max_connections=len(urls) + 10, max_keepalive_connections=0)
    async with httpx.AsyncClient(base_url=base, timeout=30, limits=limits, headers=INGEST) as http:
        before = _api_clients(probe, db)
        got: list[list[str]] = [[] for _ in urls]
        opened = [asyncio.Event() for _ in urls]

        async def one(i: int) -> None:
            async with http.stream("GET", urls[i]) as resp:
                assert resp.status_code == 200
                async for line in resp.aiter_lines():
                    if line.startswith("event: "):
                        got[i].append(line.removeprefix("event: "))
                        opened[i].set()
                        if got[i][-1] == "done":
                            return

        tasks = []
        for i in range(len(urls)):
            tasks.append(asyncio.create_task(one(i)))
            await asyncio.wait_for(opened[i].wait(), 10)
        await asyncio.sleep(0.6)  # the reader's next XREAD takes in the last streams (api.event_hub.BLOCK_MS)
        during = _api_clients(probe, db)
        publish_to("progress")
        await asyncio.sleep(0.3)
        publish_to("done")
        await asyncio.wait_for(asyncio.gather(*tasks), 20)
    return before, during, got


@pytest.mark.slow
def test_open_streams_share_redis_connections_and_all_get_the_events(tmp_path: Path) -> None:
    """30 event streams open on 3 sessions of one API process add a handful of Redis connections (CLIENT LIST),
    not one each, and every stream still gets its session's progress and done events."""
    from services.jobs.redis_backend import read_embedded_url

    n_streams, n_sessions = 30, 3
    with live_api(tmp_path, KEYS, log_level="WARNING", events_max_per_principal="64") as api:
        http = httpx.Client(base_url=api.base_url, timeout=10)
        sids = [
            http.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
            for _ in range(n_sessions)
        ]
        url = os.environ.get("REDIS_URL") or read_embedded_url(api.data_dir)
        assert url
        probe = redis.Redis.from_url(url)
        db = int(probe.connection_pool.connection_kwargs.get("db", 0))

        def publish_to(kind: str) -> None:
            for sid in sids:
                probe.xadd(queue.events_stream(sid, api.prefix), {"type": kind, "data": json.dumps({"processed": 1})})

        urls = [f"/v1/sessions/{sids[i % n_sessions]}/events" for i in range(n_streams)]
        try:
            before, during, got = asyncio.run(_streams_share_connections(api.base_url, urls, probe, db, publish_to))
        finally:
            probe.close()
    assert during - before <= 8, (before, during)  # one reader and a small pool, not 30 connections
    assert got == [["snapshot", "progress", "done"]] * n_streams, got
