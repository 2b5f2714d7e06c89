"""One owner per contract: a live session and a reprocess of the same scan, run by a real worker process over a
real Redis, are served the same mosaic.json fields, report fields and session extent by the API.

Both sides build mosaic.json with core.outputs.documents.mosaic_json, the extent with canvas_extent_mm and the
report with services.store.stored_report.write_version_report; the live run and the offline pipeline feed the same
prepared frames to the same deterministic registration, so their values agree to floating-point noise.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from services.jobs import job_records as jobs
from services.settings import Settings
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore
from tests.sim_cache import live_short
from tests.workers.conftest import Backend, store_scan, wait_for

pytestmark = pytest.mark.slow

ADMIN = "admin-key-0123456789abcdef"
HEADERS = {"Authorization": f"Bearer {ADMIN}"}
DONE_TIMEOUT_S = 120.0
# the paths agree to 1e-6 mm (tests/workers/test_live_pipeline.py); figures derived from them to well within this
VALUE_TOL = 1e-5
# what legitimately differs between two versions: which version it is, the mosaic's change counter (a live
# version is flushed many times, a reprocessed one written once) and the tile revisions that count those flushes
PER_VERSION_MOSAIC = {"version", "results_version", "revisions"}
PER_VERSION_REPORT = {"results_version", "mosaic_version", "plots"}


@pytest.fixture
def api(backend: Backend) -> Iterator[TestClient]:
    """Yield a started API over the backend's data dir, Redis and key prefix (an admin key sees every session)."""
    settings = Settings(
        data_dir=backend.data_dir,
        redis_url=backend.url,
        redis_prefix=backend.prefix,
        api_keys={ADMIN: ["admin"]},
        token_secret="test-secret-0123456789abcdef-0123",
    )
    with TestClient(create_app(settings)) as client:
        yield client


def reference_csv(reference_mm: np.ndarray) -> str:
    """Return reference.csv text (seq,x_mm,y_mm) of a (N, 2) reference track indexed by seq."""
    out = io.StringIO()
    out.write("seq,x_mm,y_mm\n")
    for seq, (x, y) in enumerate(reference_mm):
        if np.isfinite(x) and np.isfinite(y):
            out.write(f"{seq},{x:.6f},{y:.6f}\n")
    return out.getvalue()


def served(client: TestClient, sid: str, v: int) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """Return (mosaic.json, report, the session state's extent) the API serves for results version v."""
    mosaic = client.get(f"/v1/sessions/{sid}/mosaic.json?v={v}", headers=HEADERS)
    report = client.get(f"/v1/sessions/{sid}/report?v={v}", headers=HEADERS)
    state = client.get(f"/v1/sessions/{sid}", headers=HEADERS)
    for resp in (mosaic, report, state):
        assert resp.status_code == 200, resp.text
    extent = state.json()["extent"]
    assert extent is not None and extent["results_version"] == v
    return mosaic.json(), report.json(), extent


def without(doc: dict[str, Any], keys: set[str]) -> dict[str, Any]:
    """Return doc less `keys`."""
    return {k: v for k, v in doc.items() if k not in keys}


def assert_same(live: Any, other: Any, where: str) -> None:
    """Assert two JSON values are equal, numbers within VALUE_TOL."""
    if isinstance(live, dict):
        assert isinstance(other, dict) and set(live) == set(other), (where, sorted(set(live) ^ set(other)))
        for k in live:
            assert_same(live[k], other[k], f"{where}.{k}")
    elif isinstance(live, list):
        assert isinstance(other, list) and len(live) == len(other), where
        for i, (a, b) in enumerate(zip(live, other, strict=True)):
            assert_same(a, b, f"{where}[{i}]")
    elif isinstance(live, float) and not isinstance(other, bool):
        assert isinstance(other, int | float) and other == pytest.approx(live, abs=VALUE_TOL), (where, live, other)
    else:
        assert live == other, (where, live, other)


def test_live_and_reprocess_serve_the_same_documents(
    backend: Backend, spawn_worker: Callable[..., Any], api: TestClient
) -> None:
    spawn_worker("a")
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    scan = live_short(1)  # the API carries no mask.png
    assert scan.reference_mm is not None
    sid = store_scan(store, scan, backend.r, backend.prefix)
    wait_for(lambda: store.get_meta(sid).status == "done", DONE_TIMEOUT_S, "live status done")
    posted = api.post(
        f"/v1/sessions/{sid}/reference",
        content=reference_csv(scan.reference_mm),
        headers={**HEADERS, "Content-Type": "text/csv"},
    )
    assert posted.status_code == 200, posted.text
    live = served(api, sid, 1)

    (job,) = jobs.enqueue_jobs(backend.r, backend.prefix, "", [sid], {"method": "best"})
    wait_for(
        lambda: jobs.read_job(backend.r, backend.prefix, job).get("state") in ("done", "failed"),
        DONE_TIMEOUT_S,
        "reprocess job done",
    )
    assert jobs.read_job(backend.r, backend.prefix, job)["state"] == "done"
    assert results.current_version(sid) == 2
    assert results.read_report(sid, 2) is not None  # written by the reprocess stage, not rebuilt by the API
    again = served(api, sid, 2)

    (mosaic1, report1, extent1), (mosaic2, report2, extent2) = live, again
    assert mosaic1["status"] == mosaic2["status"] == "done"
    assert mosaic1["frames"] == {
        "processed": 40,
        "ok": 40,
        "lost": 0,
        "rejected": 0,
        "no_contact": 0,
        "in_fragments": 0,
        "keyframes": 40,
        "tracked": 0,
        "stitched": 40,
    }
    assert "compliance_per_n" in mosaic1 and mosaic1["width"] > 0
    assert_same(without(mosaic1, PER_VERSION_MOSAIC), without(mosaic2, PER_VERSION_MOSAIC), "mosaic")
    assert mosaic1["extent_mm"] == pytest.approx(mosaic2["extent_mm"], abs=VALUE_TOL)
    # the extent is the mosaic image's bounds: width x height px at px_per_mm
    x0, y0, x1, y1 = mosaic1["extent_mm"]
    k = mosaic1["px_per_mm"]
    assert (x1 - x0) * k == pytest.approx(mosaic1["width"]) and (y1 - y0) * k == pytest.approx(mosaic1["height"])

    assert_same(without(report1, PER_VERSION_REPORT), without(report2, PER_VERSION_REPORT), "report")
    for v, report in ((1, report1), (2, report2)):  # the API links each version's own plots
        assert report["plots"] == {n: f"/v1/sessions/{sid}/plots/{n}.png?v={v}" for n in ("paths", "errors")}
    assert report2["mosaic_version"] == mosaic2["version"] and report1["mosaic_version"] == mosaic1["version"]
    for v in (1, 2):
        plot = api.get(f"/v1/sessions/{sid}/plots/paths.png?v={v}", headers=HEADERS)
        assert plot.status_code == 200 and plot.content.startswith(b"\x89PNG")

    assert_same({**extent1, "results_version": 0}, {**extent2, "results_version": 0}, "extent")
