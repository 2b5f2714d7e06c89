"""A real HTTP client for the v1 API (spec §5): what `veinmosaic upload` and hospital integrators use.

It uploads a scan folder as a device would: forces a little ahead of each frame, frames in time order
(several in flight), retrying with tenacity on 503 and 429 (honouring Retry-After), 502/504 and dropped
connections or timeouts (exponential back-off); no other 4xx is ever retried. Every upload is idempotent on
the server (the same seq with the same bytes is a no-op), so retries are safe.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from email.utils import parsedate_to_datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from tenacity import RetryCallState, Retrying, retry_if_exception_type, stop_after_attempt, wait_exponential

from services.store.scan_folder import frame_name, read_scan_folder

RETRY_STATUSES = {429, 502, 503, 504}  # "retry later" answers; every other 4xx/5xx is final
CONNECTION_ERRORS = (httpx.ConnectError, httpx.ReadError, httpx.RemoteProtocolError, httpx.TimeoutException)
FORCE_LEAD_S = 0.5  # forces are sent this far ahead of each frame's timestamp
MAX_RETRY_AFTER_S = 30.0  # a longer Retry-After is waited this long
BACKOFF = wait_exponential(multiplier=0.2, max=5.0)  # 0.2, 0.4, 0.8 ... 5 s when the server names no wait


class ApiError(RuntimeError):
    """An error answer from the API: status, code and message from the spec's error body."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(f"HTTP {status} {code}: {message}")
        self.status, self.code, self.message = status, code, message


class RetryLaterError(Exception):
    """A "retry later" answer (RETRY_STATUSES), raised inside the retry loop so tenacity retries it."""

    def __init__(self, response: httpx.Response) -> None:
        super().__init__(f"HTTP {response.status_code}")
        self.response = response


def retry_after_s(response: httpx.Response, now: float | None = None) -> float | None:
    """Return the wait (s) a Retry-After header asks for (seconds or an HTTP date), None when absent or invalid."""
    value = response.headers.get("Retry-After", "").strip()
    if not value:
        return None
    try:
        wait = float(value)
    except ValueError:
        try:
            wait = parsedate_to_datetime(value).timestamp() - (time.time() if now is None else now)
        except (TypeError, ValueError, IndexError):
            return None
    return wait if wait == wait else None  # NaN is no wait


def wait_for(state: RetryCallState) -> float:
    """Return the wait (s) before the next attempt: the answer's Retry-After (capped), else exponential back-off."""
    error = state.outcome.exception() if state.outcome is not None else None
    if isinstance(error, RetryLaterError):
        asked = retry_after_s(error.response)
        if asked is not None:
            return min(max(asked, 0.0), MAX_RETRY_AFTER_S)
    return float(BACKOFF(state))


def api_error(response: httpx.Response) -> ApiError:
    """Return the ApiError of an error answer (the spec's error body, else the start of the text)."""
    try:
        err = response.json()["error"]
        return ApiError(response.status_code, str(err.get("code", "")), str(err.get("message", "")))
    except (ValueError, KeyError, TypeError, AttributeError):
        return ApiError(response.status_code, "http_error", response.text[:200])


class VeinmosaicClient:
    """A thin, retrying client for one server and one API key."""

    def __init__(
        self,
        base_url: str,
        key: str,
        timeout_s: float = 30.0,
        max_retries: int = 8,
        transport: httpx.BaseTransport | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.http = httpx.Client(
            base_url=self.base_url, headers={"Authorization": f"Bearer {key}"}, timeout=timeout_s, transport=transport
        )
        self.max_retries = max_retries
        self.sleep = sleep

    def close(self) -> None:
        """Close the connection pool."""
        self.http.close()

    def _attempt(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        response = self.http.request(method, url, **kwargs)
        if response.status_code in RETRY_STATUSES:
            raise RetryLaterError(response)
        return response

    def request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        """Return the response of a request, retrying transient failures; raise ApiError on 4xx/5xx.

        A connection error still there after the last retry is raised as is (an httpx error)."""
        retrying = Retrying(
            retry=retry_if_exception_type((RetryLaterError, *CONNECTION_ERRORS)),
            stop=stop_after_attempt(self.max_retries + 1),
            wait=wait_for,
            sleep=self.sleep,
            reraise=True,
        )
        try:
            response = retrying(self._attempt, method, url, **kwargs)
        except RetryLaterError as last:
            raise api_error(last.response) from None
        if response.status_code >= 400:
            raise api_error(response)
        return response

    def create_session(
        self, calibration: dict[str, Any], label: str, study: dict[str, str] | None = None
    ) -> dict[str, Any]:
        """Return the new session ({"id", "viewer_url", ...}); study: the examination's context (spec §5)."""
        body: dict[str, Any] = {"calibration": calibration, "label": label}
        if study:
            body["study"] = study
        return self.request("POST", "/v1/sessions", json=body).json()

    def upload_frame(self, session_id: str, seq: int, t_s: float, data: bytes, filename: str) -> int:
        """Return the HTTP status of uploading one frame (202 new, 200 already there)."""
        files = {"image": (filename, data, "application/octet-stream")}
        meta = json.dumps({"seq": int(seq), "t_s": float(t_s)})
        return self.request("POST", f"/v1/sessions/{session_id}/frames", files=files, data={"meta": meta}).status_code

    def upload_forces(self, session_id: str, samples: np.ndarray, imu: np.ndarray | None = None) -> None:
        """Upload a batch of force samples (rows t_s, f1..f4) and optionally IMU rows (t_s, tx, ty)."""
        body: dict[str, Any] = {"samples": np.asarray(samples, float).tolist()}
        if imu is not None and len(imu):
            body["imu"] = np.asarray(imu, float).tolist()
        self.request("POST", f"/v1/sessions/{session_id}/forces", json=body)

    def finish(self, session_id: str) -> None:
        """Tell the server no more uploads come for the session."""
        self.request("POST", f"/v1/sessions/{session_id}/finish")

    def session(self, session_id: str) -> dict[str, Any]:
        """Return the session's state (status, frames received/processed/lost, extent)."""
        return self.request("GET", f"/v1/sessions/{session_id}").json()

    def post_reference(self, session_id: str, csv_text: str) -> dict[str, Any]:
        """Return the accuracy report of uploading reference.csv."""
        headers = {"Content-Type": "text/csv"}
        return self.request(
            "POST", f"/v1/sessions/{session_id}/reference", content=csv_text.encode(), headers=headers
        ).json()

    def wait_done(
        self, session_id: str, timeout_s: float = 600.0, progress: Callable[[dict[str, Any]], None] | None = None
    ) -> dict[str, Any]:
        """Return the session's final state, polling until it is done (or failed); raise TimeoutError."""
        deadline = time.monotonic() + timeout_s
        while True:
            state = self.session(session_id)
            if progress:
                progress(state)
            if state.get("status") in ("done", "failed"):
                return state
            if time.monotonic() > deadline:
                raise TimeoutError(f"session not done after {timeout_s:.0f} s")
            time.sleep(0.5)

    def send(self, session_id: str, destination: str) -> str:
        """Return the job id of a send queued of the session's DICOM objects to a configured PACS destination."""
        return self.request("POST", f"/v1/sessions/{session_id}/send", json={"destination": destination}).json()["job"]

    def wait_job(self, job_id: str, timeout_s: float = 300.0) -> dict[str, Any]:
        """Return a job's final state, polling until it is done or failed; raise TimeoutError."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.request("GET", f"/v1/jobs/{job_id}").json()
            if job.get("status", job.get("state")) in ("done", "failed"):  # `state`: a server before `status`
                return job
            if time.monotonic() > deadline:
                raise TimeoutError(f"job not finished after {timeout_s:.0f} s")
            time.sleep(0.5)


def upload_scan_folder(
    client: VeinmosaicClient,
    scan_dir: str | Path,
    label: str = "",
    realtime: float = 0.0,
    parallel: int = 4,
    progress: Callable[[int, int], None] | None = None,
    on_session: Callable[[dict[str, Any]], None] | None = None,
    study: dict[str, str] | None = None,
) -> str:
    """Return the session id of a scan folder (spec §3) uploaded as a device would. study: the examination's context.

    realtime > 0 paces frames at that multiple of the recorded frame rate (1.0 = as recorded); 0 = as fast
    as the server accepts. Frames go in time order with `parallel` in flight; forces lead them.
    """
    scan_dir = Path(scan_dir)
    scan = read_scan_folder(scan_dir)
    calibration = json.loads((scan_dir / "calibration.json").read_text())
    created = client.create_session(calibration, label, study)
    session_id = created["id"]
    if on_session:
        on_session(created)
    forces = np.column_stack([scan.force_t_s, scan.forces_n])
    forces = forces[np.argsort(forces[:, 0], kind="stable")]
    imu = None
    if scan.imu_t_s is not None and scan.imu_tilt_deg is not None:
        imu = np.column_stack([scan.imu_t_s, scan.imu_tilt_deg])
        imu = imu[np.argsort(imu[:, 0], kind="stable")]
    order = np.argsort(scan.frame_t_s, kind="stable")
    sent_forces = sent_imu = 0
    t0_wall, t0_scan = time.monotonic(), float(scan.frame_t_s[order[0]])
    done = 0
    with ThreadPoolExecutor(max_workers=parallel) as pool:
        pending = []
        for i in order:
            t = float(scan.frame_t_s[i])
            if realtime > 0:
                time.sleep(max(0.0, (t - t0_scan) / realtime - (time.monotonic() - t0_wall)))
            # the last sample is held back so the final batch (with the last IMU rows) is never empty
            upto = min(int(np.searchsorted(forces[:, 0], t + FORCE_LEAD_S, side="right")), len(forces) - 1)
            if upto > sent_forces:  # with the IMU rows up to the same time, so a frame's IMU arrives with its forces
                imu_upto = 0 if imu is None else int(np.searchsorted(imu[:, 0], forces[upto - 1, 0], side="right"))
                client.upload_forces(
                    session_id, forces[sent_forces:upto], None if imu is None else imu[sent_imu:imu_upto]
                )
                sent_forces, sent_imu = upto, max(sent_imu, imu_upto)
            seq = int(scan.frame_seq[i])
            path = next(scan_dir.glob(frame_name(seq, "*")))
            pending.append(pool.submit(client.upload_frame, session_id, seq, t, path.read_bytes(), path.name))
            while len(pending) >= parallel * 2:
                pending.pop(0).result()
                done += 1
                if progress:
                    progress(done, len(scan))
        for fut in pending:
            fut.result()
            done += 1
            if progress:
                progress(done, len(scan))
    client.upload_forces(session_id, forces[sent_forces:], None if imu is None else imu[sent_imu:])
    client.finish(session_id)
    return session_id
