"""Shared helpers of the HTTP tests (keys, calibration, encoded frames, uploads)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from fastapi.testclient import TestClient

KEYS = {
    "ingest-key-a-0123456789abcdef": ["ingest"],
    "ingest-key-b-0123456789abcdef": ["ingest"],
    "view-key-0123456789abcdef": ["view"],
    "admin-key-0123456789abcdef": ["admin"],
}
WIDTH, HEIGHT = 64, 48


def auth(key: str) -> dict[str, str]:
    """Return the Authorization header for `key`."""
    return {"Authorization": f"Bearer {key}"}


INGEST = auth("ingest-key-a-0123456789abcdef")


def calibration_doc(**extra: Any) -> dict[str, Any]:
    """Return a valid calibration.json for WIDTH x HEIGHT frames."""
    doc: dict[str, Any] = {
        "image_size": [WIDTH, HEIGHT],
        "camera_matrix": [[80.0, 0.0, 31.5], [0.0, 80.0, 23.5], [0.0, 0.0, 1.0]],
        "px_per_mm": 8.0,
    }
    doc.update(extra)
    return doc


def frame_bytes(seed: int = 0, ext: str = ".png", size: tuple[int, int] = (WIDTH, HEIGHT), **kw: Any) -> bytes:
    """Return an encoded random grayscale frame (uint8 unless dtype=np.uint16, channels=3 for colour)."""
    rng = np.random.default_rng(seed)
    dtype = kw.get("dtype", np.uint8)
    shape = (size[1], size[0]) if kw.get("channels", 1) == 1 else (size[1], size[0], kw["channels"])
    img = rng.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


def meta_json(seq: int, t_s: float = 0.0) -> str:
    """Return the `meta` form field for a frame."""
    return f'{{"seq": {seq}, "t_s": {t_s}}}'


def upload(client: TestClient, session_id: str, seq: int, data: bytes, t_s: float = 0.0, **kw: Any) -> Any:
    """POST one frame; return the response."""
    headers = kw.pop("headers", INGEST)
    files = {"image": ("f.png", data, "application/octet-stream")}
    return client.post(
        f"/v1/sessions/{session_id}/frames",
        files=files,
        data={"meta": kw.pop("meta", meta_json(seq, t_s))},
        headers=headers,
    )
