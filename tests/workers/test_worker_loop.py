"""The worker loop in-process: retries then dead-letter of a failing frame, XAUTOCLAIM of abandoned entries,
delivery counts, reprocess options validation, and a reprocess job run once under its run lock."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.core.method_options import parse_options, validate_options
from services.jobs import job_records as jobs
from services.jobs import queue
from services.store.results_store import LIVE_VERSION, ResultsStore
from services.store.storage import SessionStore
from tests.sim_cache import simulated
from tests.workers.conftest import Backend, store_scan
from workers.config import Context, WorkerConfig
from workers.main import Worker


def _worker(backend: Backend, **cfg: object) -> Worker:
    config = WorkerConfig(
        data_dir=backend.data_dir, prefix=backend.prefix, consumer="unit", block_ms=50, held_block_ms=20, **cfg
    )
    ctx = Context(config, backend.r, SessionStore(backend.data_dir), ResultsStore(backend.data_dir))
    return Worker(ctx)


def _png(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def test_failing_frame_is_retried_then_dead_lettered(backend: Backend) -> None:
    r, p = backend.r, backend.prefix
    store = SessionStore(backend.data_dir)
    calib = default_calibration()
    sid = store.create_session("o" * 64, "x", calib).id
    rng = np.random.default_rng(0)
    store.put_forces(sid, [[0.0, 1, 1, 1, 1], [10.0, 1, 1, 1, 1]])
    store.put_frame(sid, 0, 0.1, _png(rng.integers(0, 255, (320, 400), dtype=np.uint8)), "png")
    store.put_frame(sid, 1, 0.2, _png(np.full((80, 100), 128, np.uint8)), "png")  # decodes, wrong size
    store.finish(sid)
    worker = _worker(backend, max_deliveries=3, claim_every_s=60.0)
    queue.ensure_groups(r, p)
    queue.enqueue_frame(r, sid, 1, p)
    deadline = time.monotonic() + 20
    while not r.xlen(queue.dead_stream(p)) and time.monotonic() < deadline:
        worker.step()
    dead = r.xrange(queue.dead_stream(p))
    assert len(dead) == 1
    fields = dead[0][1]
    assert fields[b"kind"] == b"frame" and fields[b"seq"] == b"1" and fields[b"attempt"] == b"2"
    assert b"calibration image_size" in fields[b"error"]  # the third failure's message (no patient data)
    assert ResultsStore(backend.data_dir).is_poison(sid, 1, 1)
    assert int(r.hget(queue.metrics_key(p), "dead_letters_total")) == 1
    assert r.xlen(queue.frames_stream(p)) == 0  # acknowledged and deleted
    assert r.xpending(queue.frames_stream(p), queue.GROUP)["pending"] == 0


def test_autoclaim_handles_abandoned_entries_and_counts_deliveries(backend: Backend) -> None:
    r, p = backend.r, backend.prefix
    queue.ensure_groups(r, p)
    stream = queue.jobs_stream(p)
    (job,) = jobs.enqueue_jobs(r, p, "", ["b" * 32], {})
    got = r.xreadgroup(queue.GROUP, "ghost", {stream: ">"}, count=1)  # a worker that then dies
    ((entry_id, _),) = got[0][1]
    for _ in range(2):  # two more deliveries (e.g. claimed by workers that died too)
        r.xclaim(stream, queue.GROUP, "ghost2", 0, [entry_id])
    worker = _worker(backend, claim_idle_ms=0, max_deliveries=3)
    worker.autoclaim()
    # the 4th delivery exceeds max_deliveries: dead-lettered, the job failed, the entry gone
    assert r.xlen(queue.dead_stream(p)) == 1
    assert jobs.read_job(r, p, job)["state"] == "failed"
    assert r.xpending(stream, queue.GROUP)["pending"] == 0 and r.xlen(stream) == 0
    # an abandoned entry with deliveries left is simply handled (here: a frame of an unknown session, dropped)
    queue.enqueue_frame(r, "c" * 32, 0, p)
    r.xreadgroup(queue.GROUP, "ghost", {queue.frames_stream(p): ">"}, count=1)
    worker.autoclaim()
    assert r.xpending(queue.frames_stream(p), queue.GROUP)["pending"] == 0
    assert r.xlen(queue.dead_stream(p)) == 1


def test_parse_options() -> None:
    opts, calib = parse_options({"method": "paper", "method_options": {"min_inliers": 12, "ransac_px": 3}})
    assert opts.name == "paper" and opts.min_inliers == 12 and opts.ransac_px == 3.0
    assert isinstance(opts.ransac_px, float) and calib == {}
    assert parse_options(None)[0].name == "best"
    _, calib = parse_options({"calibration": {"young_modulus_kpa": 20.0}})
    assert calib == {"young_modulus_kpa": 20.0}
    validate_options({"calibration": {"young_modulus_kpa": 20.0}}, default_calibration())
    for doc, needle in [
        ({"method": "nope"}, "unknown method"),
        ({"colour": 1}, "unknown field"),
        ({"method_options": {"min_inliers": "x"}}, "min_inliers must be a whole number"),
        ({"method_options": {"refine": 1}}, "refine must be a boolean"),
        ({"method_options": {"bogus": 1}}, "unknown option"),
        ({"method_options": {"name": "x"}}, "cannot be overridden"),
        ([], "JSON object"),
    ]:
        with pytest.raises(ValueError, match=needle):
            parse_options(doc)
    with pytest.raises(ValueError, match="young_modulus"):
        validate_options({"calibration": {"young_modulus_kpa": -1.0}}, default_calibration())
    assert parse_options({"method": "best", "source": "live"}, strict=False)[0].name == "best"


def test_finished_session_without_frames_is_done(backend: Backend) -> None:
    store = SessionStore(backend.data_dir)
    sid = store.create_session("o" * 64, "x", default_calibration()).id
    store.finish(sid)
    queue.enqueue_finish(backend.r, sid, backend.prefix)
    worker = _worker(backend)
    queue.ensure_groups(backend.r, backend.prefix)
    deadline = time.monotonic() + 10
    while store.get_meta(sid).status != "done" and time.monotonic() < deadline:
        worker.step()
    assert store.get_meta(sid).status == "done"
    results = ResultsStore(backend.data_dir)
    assert results.read_path(sid, 1) == [] and results.read_mosaic_meta(sid, 1)["status"] == "done"
    events = backend.r.xrange(queue.events_stream(sid, backend.prefix))
    assert [e[1][b"type"] for e in events] == [b"done"]
    assert not worker.register.held  # nothing kept in memory, the lease released for good
    assert backend.r.get(queue.lease_key(sid, 1, backend.prefix)) is None


def test_a_reprocess_job_runs_once_while_another_worker_holds_it(backend: Backend) -> None:
    """Two entries of one job (the reconciler re-queued it while it ran): neither runs while another worker holds
    the job's run lock; afterwards one runs and the other is dropped: one new version, not two."""
    r, p = backend.r, backend.prefix
    store = SessionStore(backend.data_dir)
    sid = store_scan(store, simulated("short", 1))
    queue.ensure_groups(r, p)
    (job,) = jobs.enqueue_jobs(r, p, "", [sid], {})
    jobs.requeue_job(r, p, jobs.read_job(r, p, job))  # the reconciler's second entry of the same job
    worker = _worker(backend, job_busy_retry_s=0.2)
    results = ResultsStore(backend.data_dir)

    def reprocessed() -> list[int]:  # versions made by reprocess jobs (1 is the live run's: the reconciler
        return [v for v in results.list_versions(sid) if v != LIVE_VERSION]  # queues the stored frames for it)

    with store.jobs.run_lock(job) as held:  # another worker is running the job
        assert held
        deadline = time.monotonic() + 20
        while r.xlen(queue.jobs_stream(p)) and time.monotonic() < deadline:
            worker.step()
        assert r.xlen(queue.jobs_stream(p)) == 0  # both entries handled ...
        assert jobs.read_job(r, p, job)["state"] == "queued"  # ... neither ran
        assert reprocessed() == []
    deadline = time.monotonic() + 120
    while jobs.read_job(r, p, job)["state"] != "done" and time.monotonic() < deadline:
        worker.step()
    assert jobs.read_job(r, p, job)["state"] == "done"
    settle = time.monotonic() + 2.0  # the second entry comes back after job_busy_retry_s and is dropped
    while time.monotonic() < settle:
        worker.step()
    assert len(reprocessed()) == 1 and results.current_version(sid) == reprocessed()[0]
    assert r.xlen(queue.jobs_stream(p)) == 0 and r.zcard(queue.delayed_key(p)) == 0
    assert store.jobs.is_finished(job)
    assert not list((store.jobs.root / "running").iterdir())  # the finished job's lock file is gone


def test_another_keys_job_is_served_while_one_key_has_many_queued(backend: Backend) -> None:
    """Fair queueing (services.jobs.job_lanes): key A queues 30 jobs, then key B one; the worker loop serves B's
    job after at most jobs_in_flight + 1 of A's while A still has most of its jobs queued (first come, first
    served would run B's job 31st)."""
    r, p = backend.r, backend.prefix
    queue.ensure_groups(r, p)
    flood = jobs.enqueue_jobs(r, p, "a" * 64, [f"{i:032x}" for i in range(30)], {"destination": "x"}, kind="send",
                              in_flight=2)  # fmt: skip
    (theirs,) = jobs.enqueue_jobs(r, p, "b" * 64, ["b" * 32], {"destination": "x"}, kind="send", in_flight=2)
    assert r.xlen(queue.jobs_stream(p)) == 2  # the stream holds jobs_in_flight; the rest wait in their lanes
    worker = _worker(backend, jobs_in_flight=2)
    served: list[str] = []

    def dispatch(stream: str, entry_id: str, fields: dict[str, str]) -> None:
        served.append(fields["job"])  # as if the job ran: the loop acks and deletes its entry

    worker.dispatcher.dispatch = dispatch  # type: ignore[method-assign]
    for _ in range(40):
        worker.step()
        if theirs in served:
            break
    assert theirs in served, served
    assert served.index(theirs) <= 3, served  # behind at most jobs_in_flight + 1 of A's 30
    assert served[: served.index(theirs)] == flood[: served.index(theirs)]  # A's own jobs keep their order
    assert len(flood) - len(served) + 1 >= 26  # A still had most of its jobs queued
    for _ in range(60):  # and A's jobs all run afterwards, each once
        worker.step()
        if len(served) == 31:
            break
    assert sorted(served) == sorted([*flood, theirs])
