"""End to end with real worker processes: live results equal the offline pipeline, exactly-once counting,
seq-ordered registration, two sessions at once, a crashed worker's session taken over, a poison frame and a
lost frame that do not block the session, and reprocessing into a new version."""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from services.core.inputs.scan import Scan
from services.core.methods import method_options
from services.core.pipeline import Reconstruction, reconstruct
from services.jobs import job_records as jobs
from services.jobs import queue
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore
from services.store.stored_report import write_version_report
from services.store.version_state import VersionState
from tests.shared_scans import SHARED_CLINICAL, clinical_until
from tests.sim_cache import live_short, offline_best
from tests.workers.conftest import Backend, store_scan, wait_for

pytestmark = pytest.mark.slow

# Live and offline feed the same prepared frames (same bytes, forces, mask, flat field) in the same order to
# the same deterministic registration, so the paths should agree to floating-point noise; 1e-6 mm is far
# below anything that matters (the probe path's accuracy is ~1 mm) yet catches any change of input or order.
PATH_TOL_MM = 1e-6
YAW_TOL_DEG = 1e-6
DONE_TIMEOUT_S = 90.0
TRACKED_PATH_MM = 0.3  # a live path with frames tracked against the offline one (RELOCALISED_MM's 0.5, less margin)


def scan_of(seed: int) -> Scan:
    """The simulated "short" scan (40 frames); no mask.png, as in a live session (the window is estimated)."""
    return live_short(seed)


def offline_of(seed: int) -> Reconstruction:
    """The offline pipeline's reconstruction of scan_of(seed) by the "best" method (made once per run)."""
    return offline_best(seed)


def path_arrays(rows: list[dict[str, Any]]) -> tuple[np.ndarray, list[str]]:
    """Return (N, 3) x_mm, y_mm, yaw_deg (NaN for null) and the statuses of path.json rows."""
    xyz = np.array([[np.nan if r[c] is None else r[c] for c in ("x_mm", "y_mm", "yaw_deg")] for r in rows], float)
    return xyz, [r["status"] for r in rows]


def assert_matches_offline(rows: list[dict[str, Any]], seed: int, off: Reconstruction | None = None) -> None:
    """Assert a live path equals the offline path (of scan_of(seed), or `off`) within PATH_TOL_MM / YAW_TOL_DEG,
    statuses identical."""
    off = off or offline_of(seed)
    live, statuses = path_arrays(rows)
    assert [r["seq"] for r in rows] == [r.seq for r in off.rows]
    assert statuses == [r.status for r in off.rows]
    want = np.array([[r.x_mm, r.y_mm, r.yaw_deg] for r in off.rows])
    assert np.array_equal(np.isnan(live), np.isnan(want))
    ok = ~np.isnan(want[:, 0])
    assert np.max(np.abs(live[ok, :2] - want[ok, :2])) <= PATH_TOL_MM
    assert np.max(np.abs(live[ok, 2] - want[ok, 2])) <= YAW_TOL_DEG


def order_log(backend: Backend, sid: str) -> list[tuple[int, int, str]]:
    """Return the (token, seq, kind) of every frame handed to registration, in order."""
    raw = backend.r.lrange(queue.debug_order_key(sid, 1, backend.prefix), 0, -1)
    out = []
    for item in raw:
        token, seq, kind = item.decode().split(":")
        out.append((int(token), int(seq), kind))
    return out


def wait_done(store: SessionStore, sid: str, timeout_s: float = DONE_TIMEOUT_S) -> None:
    """Wait until the session's status is done."""
    wait_for(lambda: store.get_meta(sid).status == "done", timeout_s, "status done")


def metric(backend: Backend, name: str) -> int:
    """Return an integer metric (0 when unset)."""
    v = backend.r.hget(queue.metrics_key(backend.prefix), name)
    return int(float(v)) if v is not None else 0


def cpu_metric(backend: Backend, name: str) -> float:
    """Return a float metric (CPU seconds; 0 when unset)."""
    v = backend.r.hget(queue.metrics_key(backend.prefix), name)
    return float(v) if v is not None else 0.0


def test_two_workers_out_of_order_equal_offline_then_reprocess(
    backend: Backend, spawn_worker: Callable[..., Any]
) -> None:
    started = time.monotonic()
    # the holder keeps the session while the next frame in order is still being prepared (the production linger_s):
    # with FAST's 5 s, a slow day's CI released it after frame 0 and the other worker took it over, a second holder
    spawn_worker("a", linger_s=30.0)
    spawn_worker("b", linger_s=30.0)
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    scan = scan_of(1)
    order = [int(i) for i in np.random.default_rng(7).permutation(len(scan))]
    assert order != sorted(order)
    sid = store_scan(store, scan, backend.r, backend.prefix, order=order)
    wait_done(store, sid)
    live_s = time.monotonic() - started
    rows = results.read_path(sid, 1)
    assert_matches_offline(rows, 1)
    # every frame prepared once and counted once
    assert queue.session_counters(backend.r, sid, backend.prefix) == {"processed": 40, "lost": 0}
    assert metric(backend, "frames_prepared_total") == 40 and metric(backend, "frames_processed_total") == 40
    # without tracking every frame is a keyframe; the CPU each stage spent on them is counted (bench/probes.py)
    assert metric(backend, "frames_keyframe_total") == 40 and metric(backend, "frames_tracked_total") == 0
    # (two-sided: a frame's SIFT alone takes over 10 ms here, and nothing takes a second)
    assert 0.01 * 40 < cpu_metric(backend, "prepare_cpu_seconds_total") < 1.0 * 40
    assert 0.002 * 40 < cpu_metric(backend, "register_keyframe_cpu_seconds_total") < 1.0 * 40
    # and each flush's CPU by part: tiles rendered, the whole images written at least at the end (two-sided: each
    # renders and encodes PNGs of the mosaic, over 5 ms in all; a flush part with nothing to do counts microseconds)
    assert metric(backend, "flushes_total") >= 1
    assert 0.005 < cpu_metric(backend, "flush_tiles_cpu_seconds_total") < 1.0 * 40
    assert 0.005 < cpu_metric(backend, "flush_images_cpu_seconds_total") < 1.0 * 40
    # the finish counted once, by part: the final refinement, the restitch and the final flush each take some
    # milliseconds and none the whole run's time; `best` moves the frames at the finish, 1 to 40 pasted again
    assert metric(backend, "sessions_finished_total") == 1
    for part in ("refine", "restitch", "final_flush"):
        assert 0.0005 < cpu_metric(backend, f"finish_{part}_wall_seconds_total") < live_s, part
    assert 1 <= metric(backend, "finish_frames_pasted_again_total") <= 40
    # one holder registered the frames, in seq order, each once
    log = order_log(backend, sid)
    assert [seq for _, seq, _ in log] == list(range(40)) and len({t for t, _, _ in log}) == 1
    meta = results.read_mosaic_meta(sid, 1)
    assert meta["status"] == "done" and meta["frames"] == {
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
    assert meta["dzi"]["max_level"] == 12 and meta["dzi"]["origin_px"] == [1792, 1792]
    assert meta["width"] > 0 and meta["extent_mm"][0] < 0 < meta["extent_mm"][2]
    # a tile left empty when refinement moved frames out of it keeps its new revision (the viewer must learn it
    # turned blank) but has no file (the route serves a transparent tile): a few at the fringe, never most
    for layer in ("vein", "force"):
        revs = meta["revisions"][layer]
        missing = [k for k in revs if not results.tile_path(sid, 1, layer, *_key(k)).exists()]
        assert revs and len(missing) <= len(revs) // 10, (layer, missing[:10], len(missing), len(revs))
    assert results.image_path(sid, 1, "mosaic.png").exists() and results.image_path(sid, 1, "force.png").exists()
    events = backend.r.xrange(queue.events_stream(sid, backend.prefix))
    kinds = [e[1][b"type"] for e in events]
    assert kinds[-1] == b"done" and b"progress" in kinds
    tails = [s for e in events for s, *_ in json.loads(e[1][b"data"])["path_tail"]]
    assert sorted(set(tails)) == list(range(40))
    assert live_s < 60, f"live processing took {live_s:.1f} s"

    # reprocess: a new version by the offline pipeline over the stored uploads; current only when complete
    (job_id,) = jobs.enqueue_jobs(backend.r, backend.prefix, "", [sid], {"method": "best"})
    wait_for(lambda: jobs.read_job(backend.r, backend.prefix, job_id).get("state") in ("done", "failed"),
             DONE_TIMEOUT_S, "job done")  # fmt: skip
    job = jobs.read_job(backend.r, backend.prefix, job_id)
    assert job["state"] == "done", job
    assert job["version"] == "2" and results.current_version(sid) == 2
    assert_matches_offline(results.read_path(sid, 2), 1)
    meta2 = results.read_mosaic_meta(sid, 2)
    assert meta2["status"] == "done" and meta2["frames"]["ok"] == 40
    assert (meta2["width"], meta2["height"]) == (meta["width"], meta["height"])
    assert metric(backend, "jobs_done_total") == 1 and metric(backend, "jobs_failed_total") == 0
    (bad,) = jobs.enqueue_jobs(backend.r, backend.prefix, "", [sid], {"method": "no-such-method"})
    wait_for(lambda: jobs.read_job(backend.r, backend.prefix, bad).get("state") == "failed", 30, "job failed")
    assert "invalid options" in jobs.read_job(backend.r, backend.prefix, bad)["error"]
    assert metric(backend, "jobs_failed_total") == 1 and results.current_version(sid) == 2


def _key(name: str) -> tuple[int, int, int]:
    level, rest = name.split("/")
    col, row = rest.split("_")
    return int(level), int(col), int(row)


def test_an_imu_sent_with_the_forces_pins_kappa_live_as_offline(
    backend: Backend, spawn_worker: Callable[..., Any]
) -> None:
    # a hand-tilted patient with an IMU (imu.csv; the shared scans have none): the view model's kappa gets the
    # IMU's as its prior, live exactly as offline (each prepared frame carries the IMU's tilts at its time)
    spawn_worker("a")
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    scan = live_short(3, tissue="stiffening", imu=True)
    off = offline_best(3, tissue="stiffening", imu=True)  # made once per run, shared with the service's test
    assert off.learned["kappa_source"] == "imu+images"
    sid = store_scan(store, scan, backend.r, backend.prefix)
    wait_done(store, sid)
    assert_matches_offline(results.read_path(sid, 1), 3, off)
    tissue = results.read_mosaic_meta(sid, 1)["tissue"]
    assert tissue["kappa_source"] == "imu+images" and tissue["kappa_imu_samples"] >= 10
    assert tissue["kappa_n_per_mm"] == pytest.approx(off.learned["kappa_n_per_mm"], rel=1e-9)


def test_two_sessions_concurrently(backend: Backend, spawn_worker: Callable[..., Any]) -> None:
    spawn_worker("a")
    spawn_worker("b")
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    s1 = store_scan(store, scan_of(1), backend.r, backend.prefix, finish=False)
    s2 = store_scan(store, scan_of(2), backend.r, backend.prefix, finish=False)
    for sid in (s1, s2):
        store.finish(sid)
        queue.enqueue_finish(backend.r, sid, backend.prefix)
    wait_done(store, s1)
    wait_done(store, s2)
    assert_matches_offline(results.read_path(s1, 1), 1)
    assert_matches_offline(results.read_path(s2, 1), 2)
    for sid in (s1, s2):
        assert queue.session_counters(backend.r, sid, backend.prefix)["processed"] == 40
        assert [seq for _, seq, _ in order_log(backend, sid)] == list(range(40))
        lags = queue.recent_lags(backend.r, sid, backend.prefix)  # one upload-to-placement lag per frame
        assert len(lags) == 40 and all(0.0 <= v < 300.0 for v in lags)


def test_crashed_worker_session_is_taken_over(backend: Backend, spawn_worker: Callable[..., Any]) -> None:
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    # uploaded faster than it places them, the victim is behind: with behind_lag_s 1.5 it would flush (and write
    # state.json) only every 2 s and have placed every frame before its state showed 8; at 5 s it flushes every 0.3 s
    victim = spawn_worker("victim", behind_lag_s=5.0)
    time.sleep(1.0)  # let it start before uploads begin
    scan = scan_of(1)
    # upload at ~25 frames/s while the victim works; kill it once it has registered some frames
    import threading

    sids: list[str] = []
    uploader = threading.Thread(
        target=lambda: sids.append(store_scan(store, scan, backend.r, backend.prefix, pause_s=0.04)), daemon=True
    )
    uploader.start()
    wait_for(lambda: bool(sids) or len(store.list_sessions()) == 1, 20, "session created")
    sid = store.list_sessions()[0]
    wait_for(lambda: (results.read_state(sid, 1) or VersionState()).cursor >= 8, 30, "victim registered 8 frames")
    victim.send_signal(signal.SIGKILL)
    victim.wait(timeout=10)
    state_at_kill = results.read_state(sid, 1)
    assert state_at_kill is not None and state_at_kill.cursor < 40 and not state_at_kill.finished
    spawn_worker("heir")
    uploader.join(timeout=30)
    wait_done(store, sid)
    assert_matches_offline(results.read_path(sid, 1), 1)  # the same path as without the crash
    assert queue.session_counters(backend.r, sid, backend.prefix) == {"processed": 40, "lost": 0}
    log = order_log(backend, sid)
    tokens = sorted({t for t, _, _ in log})
    assert len(tokens) >= 2  # the heir took the lease with a newer fencing token
    for token in tokens:  # every holder handed frames to registration strictly in seq order from 0
        seqs = [s for t, s, _ in log if t == token]
        assert seqs == list(range(len(seqs)))
    assert [s for t, s, _ in log if t == tokens[-1]][-1] == 39
    # a re-delivered prepare job keeps the first file and does not count it again (never above 40); the frame the
    # victim was preparing when killed may have been written but not counted (the count follows the file's write)
    assert 40 - 1 <= metric(backend, "frames_prepared_total") <= 40


def test_poison_and_lost_frames_do_not_block(backend: Backend, spawn_worker: Callable[..., Any]) -> None:
    solo = spawn_worker("solo", lost_timeout_s=1.0)
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    scan = scan_of(1)
    bad = np.full((80, 100), 128, np.uint8)  # a valid PNG of the wrong size: prepare raises every time
    sid = store_scan(store, scan, backend.r, backend.prefix, skip=(12,), replace_frames={7: bad})
    wait_done(store, sid)
    rows = results.read_path(sid, 1)
    assert [r["seq"] for r in rows] == list(range(40))
    assert rows[7]["status"] == "rejected" and rows[7]["x_mm"] is None
    assert rows[7]["t_s"] == pytest.approx(float(scan.frame_t_s[7]))  # the stored time, though never prepared
    assert rows[12]["status"] == "lost"
    assert sum(r["status"] == "ok" for r in rows) >= 35  # the rest registers around the two gaps
    dead = backend.r.xrange(queue.dead_stream(backend.prefix))
    assert len(dead) == 1 and dead[0][1][b"seq"] == b"7" and dead[0][1][b"session"] == sid.encode()
    counters = queue.session_counters(backend.r, sid, backend.prefix)
    assert counters["processed"] == 40 and counters["lost"] == sum(r["status"] != "ok" for r in rows)
    meta = results.read_mosaic_meta(sid, 1)
    assert meta["frames"]["rejected"] == 1 and meta["frames"]["lost"] >= 1
    solo.send_signal(signal.SIGTERM)  # graceful stop: the loop ends after the current entry
    assert solo.wait(timeout=10) == 0


@pytest.mark.skipif(not SHARED_CLINICAL.is_dir(), reason="the shared reference scans are not on this machine")
def test_a_scan_in_strokes_with_dropped_frames_gives_the_offline_path_live(
    backend: Backend, spawn_worker: Callable[..., Any]
) -> None:
    # the shared clinical scan's first two strokes: a lift with frames in the air, dropped seqs (19, 26, 44); no
    # mask.png, as live. The dropped seqs are lost (missing) live as offline; the frames in the air are rejected
    # (no_contact) and the second stroke is relocalised on the first, the same way in both.
    scan = clinical_until(110, mask=False)
    off = reconstruct(scan, method_options("best"))
    spawn_worker("a")
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    sid = store_scan(store, scan, backend.r, backend.prefix)
    wait_done(store, sid)
    rows = results.read_path(sid, 1)
    assert_matches_offline(rows, 0, off)
    assert [r["stroke"] for r in rows] == [r.stroke for r in off.rows]
    assert [r["reason"] for r in rows] == [r.reason for r in off.rows]
    reasons = {r["reason"] for r in rows if r["status"] != "ok"}
    assert reasons == {"missing", "no_contact"} and max(r["stroke"] or 0 for r in rows) == 1
    frames = results.read_mosaic_meta(sid, 1)["frames"]
    assert frames["no_contact"] == sum(r["reason"] == "no_contact" for r in rows) > 10


def test_a_live_run_that_tracks_frames_gives_the_offline_path(
    backend: Backend, spawn_worker: Callable[..., Any]
) -> None:
    # the worker's live method options (worker config method_options) reach the version's options.json, and the
    # frames prepared without features (format 4) are described in registration as offline: the same path
    tracking = {"track_overlap": 0.7}
    spawn_worker("a", method_options=tracking)
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    scan = scan_of(1)
    sid = store_scan(store, scan, backend.r, backend.prefix)
    wait_done(store, sid)
    assert results.read_options(sid, 1)["method_options"] == tracking
    off = reconstruct(scan, method_options("best").with_overrides(tracking))
    assert off.rows != offline_of(1).rows  # tracking changes the registration: this is not the default path again
    assert_matches_offline(results.read_path(sid, 1), 1, off)


def test_a_live_session_behind_its_uploads_tracks_frames_and_places_every_one(
    backend: Backend, spawn_worker: Callable[..., Any]
) -> None:
    # issue 32: once a flush finds the session behind its uploads by track_lag_s (here any wait: 10 ms), the worker
    # marks it and the next frames are prepared without features; registration tracks them on keyframes
    # (track_overlap_behind), so fewer frames pay for SIFT. Every frame is still placed, about as well as offline
    spawn_worker("a", track_lag_s=0.01)
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    scan = scan_of(1)
    sid = store_scan(store, scan, backend.r, backend.prefix, pause_s=0.03)  # faster than one worker places them
    wait_done(store, sid)
    tracked = metric(backend, "frames_tracked_total")
    assert 1 <= tracked <= 40 - 10 and metric(backend, "frames_keyframe_total") == 40 - tracked  # measured 14-15
    assert queue.session_counters(backend.r, sid, backend.prefix) == {"processed": 40, "lost": 0}
    rows = results.read_path(sid, 1)
    live = np.array([[r["x_mm"], r["y_mm"]] for r in rows], float)
    off = offline_of(1).estimate_mm
    assert all(r["status"] == "ok" for r in rows)
    # not the offline path (other frames described), but within what tracking changes: 0.09-0.11 mm apart
    assert 0 < np.max(np.hypot(*(live - off).T)) < TRACKED_PATH_MM
    assert not backend.r.exists(queue.tracking_key(sid, backend.prefix))  # unmarked once it caught up
    # the frame counts count them too (documents.frame_counts): mosaic.json, the done event, and report.json (as the
    # API writes it when a reference is posted)
    frames = {"ok": 40, "keyframes": 40 - tracked, "tracked": tracked}
    assert {k: results.read_mosaic_meta(sid, 1)["frames"][k] for k in frames} == frames
    done = json.loads(backend.r.xrevrange(queue.events_stream(sid, backend.prefix), count=1)[0][1][b"data"])
    assert done["status"] == "done" and {k: done[k] for k in frames} == frames
    assert scan.reference_mm is not None
    reference = "seq,x_mm,y_mm\n" + "".join(f"{i},{x},{y}\n" for i, (x, y) in enumerate(scan.reference_mm))
    report = write_version_report(results, sid, 1, reference, range(40))
    assert {k: report["frames"][k] for k in frames} == frames


def test_a_caught_up_live_session_runs_its_finish_ahead_and_ends_with_the_offline_path(
    backend: Backend, spawn_worker: Callable[..., Any]
) -> None:
    # finish_ahead_every_s (off by default): once the workers have placed the uploads, the holder runs the finish
    # on a copy and keeps the canvas at its places; the session then finishes with the offline path all the same
    spawn_worker("a", finish_ahead_every_s=0.05)
    spawn_worker("b", finish_ahead_every_s=0.05)
    store, results = SessionStore(backend.data_dir), ResultsStore(backend.data_dir)
    sid = store_scan(store, scan_of(1), backend.r, backend.prefix, finish=False)
    wait_for(lambda: queue.session_counters(backend.r, sid, backend.prefix)["processed"] == 40, DONE_TIMEOUT_S, "all")
    wait_for(lambda: metric(backend, "finish_ahead_runs_total") >= 1, 30, "a finish run ahead")
    assert cpu_metric(backend, "finish_ahead_cpu_seconds_total") > 0
    store.finish(sid)
    queue.enqueue_finish(backend.r, sid, backend.prefix)
    wait_done(store, sid)
    assert_matches_offline(results.read_path(sid, 1), 1)
    doc = results.read_mosaic_meta(sid, 1)
    assert doc["status"] == "done"
    # the whole images and the tiles in one set of units (the canvas's, which a run ahead may change): the mosaic's
    # pixel 0 lies on a DZI pixel (to float rounding) and its size is the extent's at its px_per_mm (to the pixel)
    corner = np.subtract(doc["dzi"]["origin_px"], doc["origin_px"])
    assert np.allclose(corner, np.round(corner), atol=1e-6)
    x0, y0, x1, y1 = doc["extent_mm"]
    size_px = np.array([x1 - x0, y1 - y0]) * doc["px_per_mm"]
    assert np.allclose(size_px, [doc["width"], doc["height"]], atol=1e-6)
