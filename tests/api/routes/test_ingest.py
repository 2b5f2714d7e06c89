"""Frame and force uploads: durability, idempotency, validation, size limits and backpressure."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from api_helpers import INGEST, calibration_doc, frame_bytes, upload
from fastapi.testclient import TestClient

from services.jobs import queue


def _jobs(client: TestClient) -> list[dict[bytes, bytes]]:
    r, prefix = client.app.state.redis, client.app.state.settings.redis_prefix  # type: ignore[attr-defined]
    return [fields for _, fields in r.xrange(queue.frames_stream(prefix))]


def _frame_files(client: TestClient, sid: str) -> list[str]:
    store = client.app.state.store  # type: ignore[attr-defined]
    return sorted(p.name for p in store.frames_dir(sid).iterdir())


def test_frame_202_durable_and_queued(client: TestClient, session_id: str) -> None:
    data = frame_bytes(1)
    resp = upload(client, session_id, 7, data, t_s=0.25)
    assert resp.status_code == 202 and resp.json() == {"seq": 7, "status": "accepted"}
    store = client.app.state.store  # type: ignore[attr-defined]
    assert (store.frames_dir(session_id) / "000007.png").read_bytes() == data
    rec = store.get_frame(session_id, 7)
    assert rec is not None and rec.t_s == 0.25 and rec.ext == "png"
    assert _jobs(client) == [{b"kind": b"frame", b"session": session_id.encode(), b"seq": b"7"}]
    assert client.get(f"/v1/sessions/{session_id}", headers=INGEST).json()["frames_received"] == 1


def test_duplicate_is_200_not_requeued_and_conflict_409(client: TestClient, session_id: str) -> None:
    data = frame_bytes(1)
    assert upload(client, session_id, 0, data).status_code == 202
    dup = upload(client, session_id, 0, data)
    assert dup.status_code == 200 and dup.json()["status"] == "duplicate"
    assert len(_jobs(client)) == 1
    other = upload(client, session_id, 0, frame_bytes(2))
    assert other.status_code == 409 and other.json()["error"]["code"] == "conflict"
    other_time = upload(client, session_id, 0, data, t_s=1.0)
    assert other_time.status_code == 409
    store = client.app.state.store  # type: ignore[attr-defined]
    assert store.read_frame_bytes(session_id, 0) == data  # the first accepted bytes are kept


def test_frame_stored_but_never_queued_is_queued_by_retry(client: TestClient, session_id: str) -> None:
    data = frame_bytes(3)
    store = client.app.state.store  # type: ignore[attr-defined]
    store.put_frame(session_id, 5, 0.0, data, "png")  # as if Redis failed right after the durable write
    assert _jobs(client) == []
    assert upload(client, session_id, 5, data).status_code == 200
    assert upload(client, session_id, 5, data).status_code == 200
    assert len(_jobs(client)) == 1


@pytest.mark.parametrize(
    ("data", "status", "code"),
    [
        (frame_bytes(0, size=(32, 48)), 422, "invalid_image"),  # wrong size
        (frame_bytes(0, channels=3), 422, "invalid_image"),  # colour
        (b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, 422, "invalid_image"),  # corrupt PNG
        (frame_bytes(0)[:200], 422, "invalid_image"),  # truncated PNG
        (b"GIF89a" + b"\x00" * 100, 415, "unsupported_media_type"),
        (b"%PDF-1.4 hello", 415, "unsupported_media_type"),
    ],
)
def test_bad_images_rejected(client: TestClient, session_id: str, data: bytes, status: int, code: str) -> None:
    resp = upload(client, session_id, 0, data)
    assert resp.status_code == status
    assert resp.json()["error"]["code"] == code
    assert _frame_files(client, session_id) == [] and _jobs(client) == []


@pytest.mark.parametrize(("ext", "dtype"), [(".tif", np.uint16), (".tif", np.uint8), (".jpg", np.uint8)])
def test_tiff_and_jpeg_accepted(client: TestClient, session_id: str, ext: str, dtype: type) -> None:
    resp = upload(client, session_id, 0, frame_bytes(0, ext=ext, dtype=dtype))
    assert resp.status_code == 202, resp.text
    assert set(_frame_files(client, session_id)) == {
        "000000.json",
        "000000" + (".tif" if ext == ".tif" else ".jpg"),
    }


@pytest.mark.parametrize(
    ("meta", "status"),
    [
        ('{"seq": 1', 400),
        ('{"seq": 1, "t_s": NaN}', 422),
        ('{"seq": -1, "t_s": 0}', 422),
        ('{"seq": 1.5, "t_s": 0}', 422),
        ('{"seq": "1", "t_s": 0}', 422),
        ('{"seq": 1, "t_s": 0, "x": 1}', 422),
        ('{"t_s": 0}', 422),
    ],
)
def test_bad_meta(client: TestClient, session_id: str, meta: str, status: int) -> None:
    resp = upload(client, session_id, 0, frame_bytes(0), meta=meta)
    assert resp.status_code == status
    if status == 422:
        assert resp.json()["error"]["message"].startswith("meta.")


def test_too_large_413(make_client: Callable[..., TestClient]) -> None:
    client = make_client(max_frame_bytes=1000)
    sid = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    big = frame_bytes(0)  # random pixels do not compress: about 3 kB
    assert len(big) > 1000
    resp = upload(client, sid, 0, big)
    assert resp.status_code == 413 and resp.json()["error"]["code"] == "payload_too_large"
    # the Content-Length guard refuses a request far above the limit before reading it
    huge = upload(client, sid, 0, b"\x89PNG\r\n\x1a\n" + b"\x00" * 400_000)
    assert huge.status_code == 413
    assert _frame_files(client, sid) == []


def test_backpressure_503_nothing_stored(make_client: Callable[..., TestClient]) -> None:
    client = make_client(queue_max_depth=2, retry_after_s=7)
    sid = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    assert upload(client, sid, 0, frame_bytes(0)).status_code == 202
    assert upload(client, sid, 1, frame_bytes(1)).status_code == 202
    resp = upload(client, sid, 2, frame_bytes(2))
    assert resp.status_code == 503
    assert resp.headers["Retry-After"] == "7" and resp.json()["error"]["code"] == "queue_full"
    assert client.app.state.store.get_frame(sid, 2) is None  # type: ignore[attr-defined]
    assert len(_jobs(client)) == 2
    # a re-send of an accepted frame is still a no-op 200 under backpressure
    assert upload(client, sid, 1, frame_bytes(1)).status_code == 200


def test_a_key_over_its_frame_quota_gets_429_and_other_keys_are_unaffected(
    make_client: Callable[..., TestClient],
) -> None:
    """quota_frames_per_key new frames per key and window (over all its sessions); the next new frame is 429
    quota_exceeded with Retry-After, nothing stored or queued; re-sends of accepted frames stay 200, refused
    uploads (409) take no unit, and another key uploads on."""
    client = make_client(quota_frames_per_key=3, quota_window_s=3600)
    other = {"Authorization": "Bearer ingest-key-b-0123456789abcdef"}
    one, two = (client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
                for _ in range(2))  # fmt: skip
    theirs = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=other).json()["id"]
    assert [upload(client, one, seq, frame_bytes(seq)).status_code for seq in (0, 1)] == [202, 202]
    assert upload(client, one, 0, frame_bytes(0)).status_code == 200  # a re-send is no new frame
    far = upload(client, two, 0, frame_bytes(5), t_s=0.0)
    assert far.status_code == 202
    refused = upload(client, two, 1, frame_bytes(6))  # the key's fourth new frame, in another session
    assert refused.status_code == 429, refused.text
    assert 1 <= int(refused.headers["Retry-After"]) <= 3600
    error = refused.json()["error"]
    assert error["code"] == "quota_exceeded" and "3 frames per 3600 s" in error["message"]
    assert client.app.state.store.get_frame(two, 1) is None  # type: ignore[attr-defined]
    assert len(_jobs(client)) == 3
    assert upload(client, one, 1, frame_bytes(1)).status_code == 200  # re-sends still answered
    assert [upload(client, theirs, s, frame_bytes(s), headers=other).status_code for s in range(3)] == [202] * 3


def test_a_refused_frame_gives_its_quota_unit_back(make_client: Callable[..., TestClient]) -> None:
    client = make_client(quota_frames_per_key=2, max_session_span_s=10.0)
    sid = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    assert upload(client, sid, 0, frame_bytes(0), t_s=0.0).status_code == 202
    for _ in range(3):  # refused by the store after the quota was counted: 409, the unit comes back
        late = upload(client, sid, 1, frame_bytes(1), t_s=1000.0)
        assert late.status_code == 409 and late.json()["error"]["code"] == "implausible_timestamp"
    assert upload(client, sid, 1, frame_bytes(1), t_s=1.0).status_code == 202
    assert upload(client, sid, 2, frame_bytes(2), t_s=2.0).status_code == 429


@pytest.mark.parametrize(
    "body",
    [
        b'{"samples": [[0.0, 1, 2, 3, NaN]]}',
        b'{"samples": [[0.0, 1, 2, 3, Infinity]]}',
        b'{"samples": [[0.0, 1, 2, 3, 1e999]]}',
        b'{"samples": [[0.0, 1, 2, 3]]}',
        b'{"samples": [[0.0, 1, 2, 3, 4, 5]]}',
        b'{"samples": [[0.0, 1, 2, 3, "4"]]}',
        b'{"samples": [[0.0, 1, 2, 3, 4]], "imu": [[0.0, 1.0]]}',
        b'{"samples": [[0.0, 1, 2, 3, 4]], "extra": 1}',
    ],
)
def test_bad_forces_422(client: TestClient, session_id: str, body: bytes) -> None:
    headers = {**INGEST, "Content-Type": "application/json"}
    resp = client.post(f"/v1/sessions/{session_id}/forces", content=body, headers=headers)
    assert resp.status_code == 422, resp.text
    assert resp.json()["error"]["code"] == "validation_error"
    store = client.app.state.store  # type: ignore[attr-defined]
    assert len(store.merged_forces(session_id)[0]) == 0


def test_overlapping_force_batches_merged(client: TestClient, session_id: str) -> None:
    t_late = np.arange(5, 15) / 100.0  # sent first, overlaps the next batch on t = 0.05..0.09
    t_early = np.arange(0, 10) / 100.0
    for t in (t_late, t_early):
        samples = [[float(ti), 1.0, 2.0, 3.0, 4.0] for ti in t]
        imu = [[float(ti), 0.5, -0.5] for ti in t]
        resp = client.post(f"/v1/sessions/{session_id}/forces", json={"samples": samples, "imu": imu}, headers=INGEST)
        assert resp.status_code == 202 and resp.json() == {"accepted": 10, "imu_accepted": 10}
    store = client.app.state.store  # type: ignore[attr-defined]
    t, f = store.merged_forces(session_id)
    np.testing.assert_array_equal(t, np.arange(0, 15) / 100.0)  # exact: same float64 values round-trip JSON
    assert f.shape == (15, 4) and (f == [1, 2, 3, 4]).all()
    ti, tilt = store.merged_imu(session_id)
    assert len(ti) == 15 and tilt.shape == (15, 2)


def test_too_many_force_samples_413(make_client: Callable[..., TestClient]) -> None:
    client = make_client(max_force_samples=10)
    sid = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    samples = [[i / 100.0, 0, 0, 0, 0] for i in range(11)]
    resp = client.post(f"/v1/sessions/{sid}/forces", json={"samples": samples}, headers=INGEST)
    assert resp.status_code == 413


def test_meta_is_read_as_json_whatever_its_field_order_and_spacing(client: TestClient, session_id: str) -> None:
    meta = '{\n  "t_s": 2 ,  "seq": 4\n}'  # t_s first, an integer time, newlines and spaces
    resp = upload(client, session_id, 4, frame_bytes(4), meta=meta)
    assert resp.status_code == 202 and resp.json() == {"seq": 4, "status": "accepted"}
    rec = client.app.state.store.get_frame(session_id, 4)  # type: ignore[attr-defined]
    assert rec is not None and rec.seq == 4 and rec.t_s == 2.0


def test_an_upload_without_its_meta_part_is_422_naming_meta(client: TestClient, session_id: str) -> None:
    files = {"image": ("f.png", frame_bytes(0), "application/octet-stream")}
    resp = client.post(f"/v1/sessions/{session_id}/frames", files=files, headers=INGEST)
    assert resp.status_code == 422 and "meta" in resp.text, resp.text
    assert _frame_files(client, session_id) == []  # nothing stored
