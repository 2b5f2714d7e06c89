"""SessionStore: durable atomic writes, frame idempotency and conflicts, force merging, closed sessions."""

from __future__ import annotations

import hashlib
import json
import os
import threading
from pathlib import Path

import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.store import storage
from services.store.durable import atomic_write_bytes
from services.store.storage import (
    ConflictError,
    SessionClosedError,
    SessionNotFoundError,
    SessionStore,
)


@pytest.fixture
def store(tmp_path: Path) -> SessionStore:
    return SessionStore(tmp_path)


@pytest.fixture
def sid(store: SessionStore) -> str:
    return store.create_session("f" * 64, "label", default_calibration(64, 48)).id


def _fail_replace(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    raise OSError("simulated crash between write and rename")


def test_atomic_write_crash_keeps_old_content_and_no_partial_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "x.json"
    atomic_write_bytes(target, b"old")
    monkeypatch.setattr(storage.os, "replace", _fail_replace)
    with pytest.raises(OSError, match="simulated crash"):
        atomic_write_bytes(target, b"new content")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]  # the temp file was removed too
    with pytest.raises(OSError):
        atomic_write_bytes(tmp_path / "fresh.bin", b"data")
    assert not (tmp_path / "fresh.bin").exists()


def test_crash_before_commit_record_leaves_no_frame_and_retry_succeeds(
    store: SessionStore, sid: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_replace = os.replace

    def replace_image_only(src: str | os.PathLike, dst: str | os.PathLike) -> None:
        if str(dst).endswith(".json"):
            raise OSError("simulated crash before the commit record")
        real_replace(src, dst)

    monkeypatch.setattr(storage.os, "replace", replace_image_only)
    with pytest.raises(OSError):
        store.put_frame(sid, 0, 0.0, b"first bytes", "png")
    monkeypatch.setattr(storage.os, "replace", real_replace)
    assert store.get_frame(sid, 0) is None and store.count_frames(sid) == 0
    # never acknowledged, so a retry with other bytes is a fresh upload, not a conflict
    assert store.put_frame(sid, 0, 0.0, b"second bytes", "png") == "created"
    assert store.read_frame_bytes(sid, 0) == b"second bytes"


def test_put_frame_idempotent_and_conflicts(store: SessionStore, sid: str) -> None:
    assert store.put_frame(sid, 3, 0.5, b"abc", "png") == "created"
    assert store.put_frame(sid, 3, 0.5, b"abc", "png") == "duplicate"
    with pytest.raises(ConflictError):
        store.put_frame(sid, 3, 0.5, b"abd", "png")
    with pytest.raises(ConflictError):
        store.put_frame(sid, 3, 0.6, b"abc", "png")
    rec = store.get_frame(sid, 3)
    assert rec is not None and rec.size == 3 and rec.t_s == 0.5
    assert store.read_frame_bytes(sid, 3) == b"abc"
    assert store.count_frames(sid) == 1


def test_concurrent_same_seq_creates_once(store: SessionStore, sid: str) -> None:
    results: list[str] = []
    threads = [
        threading.Thread(target=lambda: results.append(store.put_frame(sid, 1, 0.0, b"x" * 1000, "png")))
        for _ in range(8)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(results) == ["created"] + ["duplicate"] * 7


def _run_threads(targets: list) -> None:
    threads = [threading.Thread(target=t) for t in targets]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)


def test_concurrent_same_seq_different_bytes_one_wins_and_image_matches(store: SessionStore, sid: str) -> None:
    outcomes: list[str] = []

    def upload(k: int) -> None:
        try:
            outcomes.append(store.put_frame(sid, 3, 0.0, bytes([k]) * 5000, "png"))
        except ConflictError:
            outcomes.append("conflict")

    _run_threads([lambda k=k: upload(k) for k in range(12)])
    assert sorted(outcomes) == ["conflict"] * 11 + ["created"]
    record = store.get_frame(sid, 3)
    assert record is not None
    stored = store.frame_path(sid, 3).read_bytes()
    assert hashlib.sha256(stored).hexdigest() == record.sha256  # the image is the committed upload's, not a loser's


def test_uploads_racing_finish_are_all_counted_or_refused(store: SessionStore, sid: str) -> None:
    created: list[int] = []
    refused: list[int] = []

    def upload(seq: int) -> None:
        try:
            store.put_frame(sid, seq, seq / 10, bytes([seq % 256]) * 2000, "png")
            created.append(seq)
        except SessionClosedError:
            refused.append(seq)

    _run_threads([lambda s=s: upload(s) for s in range(40)] + [lambda: store.finish(sid)])
    meta = store.get_meta(sid)
    assert len(created) + len(refused) == 40
    assert meta.frames_expected == len(created) == store.count_frames(sid)  # none committed after finish


def test_concurrent_first_uploads_agree_on_one_time_anchor(store: SessionStore, sid: str) -> None:
    def upload(seq: int) -> None:
        store.put_frame(sid, seq, 100.0 + seq, b"x" * (seq + 1), "png", max_span_s=3600)

    _run_threads([lambda s=s: upload(s) for s in range(8)])
    anchor = store.time_anchor(sid)
    assert anchor is not None and 100.0 <= anchor <= 107.0
    assert store.count_frames(sid) == 8


def test_list_frames_sorted_and_ignores_temp_files(store: SessionStore, sid: str) -> None:
    for seq in (10, 2, 7):
        store.put_frame(sid, seq, seq / 10.0, bytes([seq]), "png")
    (store.frames_dir(sid) / ".000099.json.dead.tmp").write_bytes(b"partial")
    assert [r.seq for r in store.list_frames(sid)] == [2, 7, 10]
    assert store.count_frames(sid) == 3


def test_finish_closes_uploads_but_duplicates_stay_noops(store: SessionStore, sid: str) -> None:
    store.put_frame(sid, 0, 0.0, b"a", "png")
    meta = store.finish(sid, now=123.0)
    assert (meta.status, meta.finished_at, meta.frames_expected) == ("processing", 123.0, 1)
    assert store.finish(sid, now=999.0).finished_at == 123.0  # idempotent
    assert store.put_frame(sid, 0, 0.0, b"a", "png") == "duplicate"
    with pytest.raises(SessionClosedError):
        store.put_frame(sid, 1, 0.0, b"b", "png")
    with pytest.raises(SessionClosedError):
        store.put_forces(sid, [[0, 1, 2, 3, 4]])
    assert store.set_status(sid, "done").status == "done"


def test_merged_forces_sorted_dedup_latest_wins(store: SessionStore, sid: str) -> None:
    store.put_forces(sid, [[0.2, 1, 1, 1, 1], [0.3, 1, 1, 1, 1]])
    store.put_forces(sid, [[0.0, 2, 2, 2, 2], [0.2, 9, 9, 9, 9]], imu=[[0.0, 1.0, 2.0]])
    store.put_forces(sid, [[0.0, 2, 2, 2, 2], [0.2, 9, 9, 9, 9]])  # exact re-send: stored once
    t, f = store.merged_forces(sid)
    np.testing.assert_array_equal(t, [0.0, 0.2, 0.3])
    np.testing.assert_array_equal(f[:, 0], [2, 9, 1])  # at t = 0.2 the later batch wins
    assert len(list((store.session_dir(sid) / "raw" / "forces").iterdir())) == 2
    ti, tilt = store.merged_imu(sid)
    np.testing.assert_array_equal(ti, [0.0])
    np.testing.assert_array_equal(tilt, [[1.0, 2.0]])
    batch = next((store.session_dir(sid) / "raw" / "forces").iterdir())
    assert set(json.loads(batch.read_bytes())) == {"samples"}  # stored as received


def test_merged_forces_incremental_equals_a_fresh_merge(store: SessionStore, sid: str, tmp_path: Path) -> None:
    """Merging only the batches new since the last call (appended when later than every sample merged, merged
    again where a batch overlaps) gives what a fresh process merging all of them gives, ties won by the later
    arrival, also when a batch named earlier appears after a later one was merged."""
    rng = np.random.default_rng(7)
    for k in range(30):
        t0 = 0.1 * k - (0.15 if k % 4 == 0 else 0.0)  # every fourth batch overlaps the one before
        rows = [[round(t0 + 0.01 * j, 2), *rng.uniform(0, 9, 4)] for j in range(12)]
        store.put_forces(sid, rows)
        t_inc, f_inc = store.merged_forces(sid)  # incremental: one new batch per call
    fresh = SessionStore(store.data_dir)
    t_all, f_all = fresh.merged_forces(sid)
    np.testing.assert_array_equal(t_inc, t_all)
    np.testing.assert_array_equal(f_inc, f_all)
    assert np.all(np.diff(t_inc) > 0)
    # a batch renamed into place late, named before the last one merged: the listing is no longer an extension
    bdir = store.session_dir(sid) / "raw" / "forces"
    (bdir / f"{0:019d}-{'0' * 16}.json").write_text(json.dumps({"samples": [[0.1, 7, 7, 7, 7], [99.0, 1, 2, 3, 4]]}))
    t_late, f_late = store.merged_forces(sid)
    t_ref, f_ref = SessionStore(store.data_dir).merged_forces(sid)
    np.testing.assert_array_equal(t_late, t_ref)
    np.testing.assert_array_equal(f_late, f_ref)
    assert t_late[-1] == 99.0 and len(t_late) == len(t_all) + 1  # its new sample is in
    np.testing.assert_array_equal(f_late[t_late == 0.1], f_all[t_all == 0.1])  # at t = 0.1 the later arrival wins


def test_merged_forces_covering_a_time_reads_no_batch_it_does_not_need(store: SessionStore, sid: str) -> None:
    """A frame's preparation asks for samples up to its time: what was merged already is returned while it reaches
    that time (the batches are not listed again), and the batches since are merged once it does not."""
    store.put_forces(sid, [[0.0, 1, 1, 1, 1], [1.0, 2, 2, 2, 2]])
    assert store.merged_forces(sid)[0].tolist() == [0.0, 1.0]
    store.put_forces(sid, [[2.0, 3, 3, 3, 3]])
    assert store.merged_forces(sid, covering_t_s=0.5)[0].tolist() == [0.0, 1.0]  # covered: the new batch not read
    assert store.merged_forces(sid, covering_t_s=1.5)[0].tolist() == [0.0, 1.0, 2.0]  # not covered: merged
    store.put_forces(sid, [[3.0, 4, 4, 4, 4]])
    assert store.merged_forces(sid)[0].tolist() == [0.0, 1.0, 2.0, 3.0]  # without a time: every batch, as before


def test_bad_force_rows_rejected(store: SessionStore, sid: str) -> None:
    with pytest.raises(ValueError, match="finite"):
        store.put_forces(sid, [[0.0, 1, 2, 3, float("nan")]])
    with pytest.raises(ValueError, match="5 numbers"):
        store.put_forces(sid, [[0.0, 1, 2, 3]])
    assert len(store.merged_forces(sid)[0]) == 0


def test_session_ids_are_validated(store: SessionStore, sid: str) -> None:
    for bad in ("../" + sid, sid.upper(), "", "0" * 32):
        with pytest.raises(SessionNotFoundError):
            store.get_meta(bad)
    meta = store.get_meta(sid)
    assert meta.owner == "f" * 64 and meta.calibration["image_size"] == [64, 48]
    assert store.calibration(sid) == default_calibration(64, 48)
    assert store.list_sessions() == [sid]
    assert store.writable()


def test_load_frame_decodes(store: SessionStore, sid: str) -> None:
    import cv2

    img = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    store.put_frame(sid, 0, 0.0, cv2.imencode(".png", img)[1].tobytes(), "png")
    np.testing.assert_array_equal(store.load_frame(sid, 0), img)  # PNG is lossless: exact
