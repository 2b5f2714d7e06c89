"""Durable local-disk store of a session's raw uploads (spec §3 layout under data_dir/sessions/<id>/).

Layout of one session directory:
    session.json               SessionMeta (owner key fingerprint, never the key; label; calibration; status)
    calibration.json           spec §3 calibration document
    raw/frames/<seq:06d>.<ext> frame bytes exactly as uploaded (png | tif | jpg)
    raw/frames/<seq:06d>.json  FrameRecord: the commit record of that frame (a frame exists iff this exists)
    raw/forces/<batch>.json    one accepted force batch, never modified: {"samples": [[t_s, f1..f4], ...]}
    raw/imu/<batch>.json       one accepted IMU batch, never modified: {"imu": [[t_s, tx_deg, ty_deg], ...]}
Every write goes to a temporary file in the same directory, is fsynced, renamed over the target and the
directory fsynced; writers of one session are serialised by an flock on <session>/.lock (works across
processes on one host). Batch names sort in arrival order: <time_ns:019d>-<sha256[:16]>.json.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from services.core.inputs.calibration import Calibration, parse_calibration
from services.core.inputs.image_header import check_header, read_header
from services.core.inputs.study import StudyContext, parse_study
from services.store.durable import atomic_write_bytes, directory_lock, fsync_dir, replace_bytes
from services.store.job_ledger import JobLedger

SessionStatus = Literal["receiving", "processing", "done", "failed"]
STATUSES: tuple[str, ...] = ("receiving", "processing", "done", "failed")
FRAME_EXTENSIONS: tuple[str, ...] = ("png", "tif", "jpg")
MAX_SEQ = 999_999
_BATCH_CACHE_MAX = 20_000
_MERGED_CACHE_MAX = 64  # sessions whose merged batches a process keeps (~1 MB for a 4-minute examination)
_SESSION_ID = re.compile(r"^[0-9a-f]{32}$")


class StorageError(Exception):
    """Base class of the store's errors."""


class SessionNotFoundError(StorageError):
    """No session with that id (or a malformed id)."""


class ConflictError(StorageError):
    """The upload contradicts one already stored (same seq, different bytes or timestamp)."""


class SessionClosedError(StorageError):
    """The session was finished: it accepts no more uploads."""


class ImplausibleTimeError(StorageError):
    """An upload's timestamp is too far from the session's first one (the time anchor)."""


@dataclass(frozen=True)
class SessionMeta:
    """session.json: owner is sha256(api key) hex; created/finished_at are Unix seconds."""

    id: str
    owner: str
    label: str
    calibration: dict[str, Any]
    created: float
    status: str = "receiving"
    finished_at: float | None = None
    frames_expected: int | None = None
    error: str | None = None
    study: dict[str, str] | None = None  # the study context (patient data: owner and admins only, never logged)

    @property
    def accepting_uploads(self) -> bool:
        """Return True while the session is receiving (finish not yet called)."""
        return self.finished_at is None and self.status == "receiving"


@dataclass(frozen=True)
class FrameRecord:
    """One committed frame: seq, device time t_s (s), file extension, sha256 hex, size (bytes), arrival."""

    seq: int
    t_s: float
    ext: str
    sha256: str
    size: int
    received_at: float


def _json_bytes(doc: Any) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=False, sort_keys=True).encode()


def _finite_rows(rows: Sequence[Sequence[float]] | np.ndarray, width: int, name: str) -> np.ndarray:
    arr = np.asarray(rows, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, width))
    if arr.ndim != 2 or arr.shape[1] != width:
        raise ValueError(f"{name}: expected rows of {width} numbers, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: every number must be finite")
    return arr


def _merge_rows(batches: list[np.ndarray], width: int) -> np.ndarray:
    """Return rows of all batches (arrival order) sorted by t (col 0); for equal t the latest arrival wins."""
    if not batches:
        return np.zeros((0, width))
    rows = np.concatenate(batches, axis=0)[::-1]  # latest first, so np.unique keeps the latest
    _, first = np.unique(rows[:, 0], return_index=True)
    return rows[first]


def _appended(merged: np.ndarray, fresh: np.ndarray) -> np.ndarray:
    """Return _merge_rows([merged, fresh]) for rows already merged and rows of later batches, merged: appended
    as they are when every fresh row is later than the last merged one (a probe's batches arrive in time order,
    so this is the usual case, and it does not re-sort a long examination's samples per frame), else re-merged."""
    if len(merged) and len(fresh) and fresh[0, 0] <= merged[-1, 0]:
        return _merge_rows([merged, fresh], merged.shape[1])
    return np.concatenate([merged, fresh], axis=0)


def _batch_names(bdir: Path) -> list[str]:
    """Return the batch file names in bdir in arrival order (os.listdir: a glob cost 10 ms at 2400 batches)."""
    try:
        names = os.listdir(bdir)
    except FileNotFoundError:
        return []
    return sorted(n for n in names if n[:1].isdigit() and n.endswith(".json"))


class SessionStore:
    """Sessions on local disk under data_dir/sessions; safe for several threads and processes on one host."""

    def __init__(self, data_dir: Path, max_frame_side: int | None = None) -> None:
        """Open the store under data_dir; with max_frame_side, frames larger a side are refused from their header."""
        self.data_dir = Path(data_dir)
        self.max_frame_side = max_frame_side
        self.root = self.data_dir / "sessions"
        self.root.mkdir(parents=True, exist_ok=True)
        self._batch_cache: dict[Path, np.ndarray] = {}
        self._merged_cache: dict[Path, tuple[list[str], np.ndarray]] = {}  # batch dir -> (names merged, rows)
        self.jobs = JobLedger(self.data_dir / "jobs")

    # ----- paths and locking -------------------------------------------------------------------------
    def session_dir(self, session_id: str) -> Path:
        """Return the directory of an existing session; raise SessionNotFoundError otherwise."""
        if not isinstance(session_id, str) or not _SESSION_ID.match(session_id):
            raise SessionNotFoundError("no such session")
        path = self.root / session_id
        if not (path / "session.json").is_file():
            raise SessionNotFoundError("no such session")
        return path

    def frames_dir(self, session_id: str) -> Path:
        """Return the directory raw/frames of a session (frame files and their .json commit records)."""
        return self.session_dir(session_id) / "raw" / "frames"

    @contextlib.contextmanager
    def _locked(self, session_id: str) -> Iterator[Path]:
        path = self.session_dir(session_id)
        with directory_lock(path):
            yield path

    # ----- sessions ------------------------------------------------------------------------------------
    def create_session(
        self,
        owner: str,
        label: str,
        calibration: Calibration,
        now: float | None = None,
        study: StudyContext | None = None,
    ) -> SessionMeta:
        """Return the metadata of a session created now with a fresh unguessable id (uuid4 hex)."""
        session_id = uuid.uuid4().hex
        meta = SessionMeta(
            id=session_id,
            owner=owner,
            label=label,
            calibration=calibration.to_dict(),
            created=time.time() if now is None else now,
            study=study.to_dict() if study is not None else None,
        )
        tmp_dir = self.root / f".{session_id}.tmp"
        try:
            for sub in ("raw/frames", "raw/forces", "raw/imu", "raw/digests"):
                (tmp_dir / sub).mkdir(parents=True)
            atomic_write_bytes(tmp_dir / "calibration.json", _json_bytes(meta.calibration))
            atomic_write_bytes(tmp_dir / "session.json", _json_bytes(asdict(meta)))
            for sub in ("raw", "raw/frames", "raw/forces", "raw/imu"):
                fsync_dir(tmp_dir / sub)
            os.rename(tmp_dir, self.root / session_id)  # the session appears whole or not at all
        except BaseException:
            shutil.rmtree(tmp_dir, ignore_errors=True)  # a full disk leaves nothing behind
            raise
        fsync_dir(self.root)
        return meta

    def get_meta(self, session_id: str) -> SessionMeta:
        """Return the session's metadata; raise SessionNotFoundError."""
        doc = json.loads((self.session_dir(session_id) / "session.json").read_bytes())
        return SessionMeta(**doc)

    def list_sessions(self) -> list[str]:
        """Return the ids of all sessions (sorted)."""
        return sorted(p.name for p in self.root.iterdir() if _SESSION_ID.match(p.name))

    def calibration(self, session_id: str) -> Calibration:
        """Return the session's validated Calibration."""
        return parse_calibration(self.get_meta(session_id).calibration)

    def study(self, session_id: str) -> StudyContext | None:
        """Return the session's study context (patient data), or None when it was created without one."""
        return parse_study(self.get_meta(session_id).study)

    def _write_meta(self, path: Path, meta: SessionMeta) -> None:
        atomic_write_bytes(path / "session.json", _json_bytes(asdict(meta)))

    def finish(self, session_id: str, now: float | None = None) -> SessionMeta:
        """Return the meta of the session marked finished (status processing, frames_expected fixed); idempotent."""
        with self._locked(session_id) as path:
            meta = self.get_meta(session_id)
            if meta.finished_at is not None:
                return meta
            meta = replace(
                meta,
                status="processing" if meta.status == "receiving" else meta.status,
                finished_at=time.time() if now is None else now,
                frames_expected=self.count_frames(session_id),
            )
            self._write_meta(path, meta)
            return meta

    def set_status(self, session_id: str, status: str, error: str | None = None) -> SessionMeta:
        """Return the meta with status set (receiving/processing/done/failed; `error` a short non-patient message)."""
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, got {status!r}")
        with self._locked(session_id) as path:
            meta = replace(self.get_meta(session_id), status=status, error=error)
            self._write_meta(path, meta)
            return meta

    # ----- frames ---------------------------------------------------------------------------------------
    def get_frame(self, session_id: str, seq: int) -> FrameRecord | None:
        """Return the committed record of frame `seq`, or None when it was never stored."""
        rec = self.frames_dir(session_id) / f"{seq:06d}.json"
        try:
            return FrameRecord(**json.loads(rec.read_bytes()))
        except FileNotFoundError:
            return None

    def put_frame(
        self,
        session_id: str,
        seq: int,
        t_s: float,
        data: bytes,
        ext: str,
        now: float | None = None,
        max_span_s: float | None = None,
    ) -> Literal["created", "duplicate"]:
        """Return "created" for a frame stored durably now; "duplicate" if that seq holds the same bytes and t_s.

        Raises ConflictError if seq holds different bytes or t_s, SessionClosedError after finish,
        ImplausibleTimeError if t_s is more than max_span_s from the session's time anchor (see time_anchor).
        A failed write (a full disk) leaves neither the image nor its record behind.
        """
        if ext not in FRAME_EXTENSIONS:
            raise ValueError(f"ext must be one of {FRAME_EXTENSIONS}, got {ext!r}")
        if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= MAX_SEQ:
            raise ValueError(f"seq must be an integer in 0..{MAX_SEQ}")
        if not math.isfinite(t_s):
            raise ValueError("t_s must be finite")
        digest = hashlib.sha256(data).hexdigest()
        with self._locked(session_id):
            existing = self.get_frame(session_id, seq)
            if existing is not None:
                if existing.sha256 == digest and existing.t_s == float(t_s):
                    return "duplicate"
                raise ConflictError(f"frame {seq} was already received with different content")
            if not self.get_meta(session_id).accepting_uploads:
                raise SessionClosedError("session is finished; no more uploads are accepted")
            self._check_time(session_id, [float(t_s)], max_span_s)
            fdir = self.frames_dir(session_id)
            image = fdir / f"{seq:06d}.{ext}"
            atomic_write_bytes(image, data)
            record = FrameRecord(
                seq=seq,
                t_s=float(t_s),
                ext=ext,
                sha256=digest,
                size=len(data),
                received_at=time.time() if now is None else now,
            )
            try:
                atomic_write_bytes(fdir / f"{seq:06d}.json", _json_bytes(asdict(record)))  # the commit
            except BaseException:
                with contextlib.suppress(OSError):
                    image.unlink()  # not committed: leave nothing partial
                raise
            return "created"

    # ----- timestamps ---------------------------------------------------------------------------------
    def time_anchor(self, session_id: str) -> float | None:
        """Return the session's time anchor: the device time (s) of its first accepted upload, or None."""
        try:
            return float(json.loads((self.session_dir(session_id) / "t_anchor.json").read_bytes())["t_s"])
        except FileNotFoundError:
            return None

    def _check_time(self, session_id: str, times: Sequence[float], max_span_s: float | None) -> None:
        """Raise ImplausibleTimeError unless every time is within max_span_s of the anchor (set it if none).

        Called under the session lock, before the upload is written; the anchor is the first upload's time.
        """
        if max_span_s is None or len(times) == 0:
            return
        anchor = self.time_anchor(session_id)
        lo, hi = min(times), max(times)
        if anchor is None:
            if hi - lo > 2 * max_span_s:
                raise ImplausibleTimeError(f"timestamps span more than {2 * max_span_s:g} s")
            anchor = (lo + hi) / 2
            atomic_write_bytes(self.session_dir(session_id) / "t_anchor.json", _json_bytes({"t_s": anchor}))
        if lo < anchor - max_span_s or hi > anchor + max_span_s:
            raise ImplausibleTimeError(f"timestamp more than {max_span_s:g} s away from the session's first timestamps")

    def frame_seqs(self, session_id: str) -> list[int]:
        """Return the seqs of the committed frames, ascending (from the commit records' names only: cheap)."""
        with os.scandir(self.frames_dir(session_id)) as it:
            names = [e.name for e in it if e.name.endswith(".json") and not e.name.startswith(".")]
        return sorted(int(n[:-5]) for n in names if n[:-5].isdigit())

    def count_frames(self, session_id: str) -> int:
        """Return the number of committed frames."""
        return len(self.frame_seqs(session_id))

    def reprocess_refusal(self, meta: SessionMeta) -> tuple[str, str] | None:
        """Return (code, message) of why a session cannot be reprocessed yet (still receiving, no frames), else None."""
        if meta.finished_at is None:
            return "not_finished", "the session is still receiving uploads: finish it before reprocessing"
        if self.count_frames(meta.id) == 0:
            return "no_frames", "the session has no frames to reprocess"
        return None

    def list_frames(self, session_id: str) -> list[FrameRecord]:
        """Return all committed frames sorted by seq (the frames.csv of spec §3)."""
        fdir = self.frames_dir(session_id)
        names = sorted(p.name for p in fdir.iterdir() if p.suffix == ".json" and not p.name.startswith("."))
        records = [FrameRecord(**json.loads((fdir / n).read_bytes())) for n in names]
        return sorted(records, key=lambda r: r.seq)

    def frame_path(self, session_id: str, seq: int) -> Path:
        """Return the path of frame `seq`'s image file; raise KeyError when it was never stored."""
        rec = self.get_frame(session_id, seq)
        if rec is None:
            raise KeyError(f"frame {seq} not stored")
        return self.frames_dir(session_id) / f"{seq:06d}.{rec.ext}"

    def read_frame_bytes(self, session_id: str, seq: int) -> bytes:
        """Return frame `seq`'s bytes exactly as uploaded."""
        return self.frame_path(session_id, seq).read_bytes()

    def load_frame(self, session_id: str, seq: int, expected_size: tuple[int, int] | None = None) -> np.ndarray:
        """Return frame `seq` decoded as a 2-D uint8 or uint16 array (rows = image y).

        With expected_size (width, height px: the calibration's image_size), and whenever the store has a
        max_frame_side, the header is checked first: a frame of another size or pixel format, or larger than
        max_frame_side a side, raises BadImageError before anything is decoded.
        """
        import cv2

        data = self.read_frame_bytes(session_id, seq)
        if expected_size is not None or self.max_frame_side is not None:
            sides = [s for s in (self.max_frame_side, max(expected_size) if expected_size else None) if s]
            check_header(read_header(data), min(sides), expected_size)
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:  # over OpenCV's pixel limit
            img = None
        if img is None:
            raise StorageError(f"frame {seq} cannot be decoded")
        return img

    # ----- force and IMU batches -------------------------------------------------------------------------
    def _put_batch(self, path: Path, kind: str, rows: np.ndarray) -> str | None:
        """Return the name of the batch file holding `rows` (kind "samples" or "imu"), written unless the same batch
        was stored before (a re-send: stored once). Called under the session lock.

        Each stored batch leaves a marker named by its digest, holding its name: a re-send is found by one read, not
        by listing every batch (2400 of them in a 4-minute examination). The marker is not synced: lost in a crash,
        a re-send is stored twice, which the merge reads as one (_merge_rows: equal times, equal values).
        """
        body = _json_bytes({kind: rows.tolist()})
        digest = hashlib.sha256(body).hexdigest()[:16]
        bdir = path / "raw" / ("forces" if kind == "samples" else "imu")
        marker = path / "raw" / "digests" / f"{bdir.name}-{digest}"
        with contextlib.suppress(FileNotFoundError):
            return marker.read_text()  # the same batch re-sent: stored once
        name = f"{time.time_ns():019d}-{digest}"
        atomic_write_bytes(bdir / f"{name}.json", body)
        marker.parent.mkdir(exist_ok=True)  # a session stored before the markers has no such directory
        replace_bytes(marker, name.encode())
        return name

    def put_forces(
        self,
        session_id: str,
        samples: Sequence[Sequence[float]] | np.ndarray,
        imu: Sequence[Sequence[float]] | np.ndarray | None = None,
        max_span_s: float | None = None,
    ) -> tuple[str | None, str | None]:
        """Return the batch names (samples, IMU; None for an empty part) of one batch stored of forces and IMU rows.

        The force samples are (t_s, F1..F4 N), the optional IMU rows (t_s, tilt_x, tilt_y deg). Raises ValueError
        for non-finite values or wrong row lengths, SessionClosedError after finish, ImplausibleTimeError as
        put_frame does.
        """
        f = _finite_rows(samples, 5, "samples")
        m = _finite_rows(imu if imu is not None else [], 3, "imu")
        with self._locked(session_id) as path:
            if not self.get_meta(session_id).accepting_uploads:
                raise SessionClosedError("session is finished; no more uploads are accepted")
            self._check_time(session_id, [*f[:, 0].tolist(), *m[:, 0].tolist()], max_span_s)
            fname = self._put_batch(path, "samples", f) if len(f) else None
            iname = self._put_batch(path, "imu", m) if len(m) else None
        return fname, iname

    def _load_batch(self, path: Path, kind: str, width: int) -> np.ndarray:
        """Return one batch file's rows, parsed once per process (batch files are immutable)."""
        arr = self._batch_cache.get(path)
        if arr is None:
            arr = _finite_rows(json.loads(path.read_bytes())[kind], width, kind)
            if len(self._batch_cache) >= _BATCH_CACHE_MAX:
                self._batch_cache.clear()
            self._batch_cache[path] = arr
        return arr

    def _merged_batches(self, bdir: Path, kind: str, width: int, covering_t_s: float | None = None) -> np.ndarray:
        """Return the rows of every batch in bdir merged (_merge_rows), merging only batches new since the last call.

        Batch names sort in arrival order, so the batches of the last call are a prefix of the listing and the
        new ones arrived later (they win ties, as in a full merge). A listing that does not extend the last one
        (a batch renamed into place late by another process) is merged whole again. With covering_t_s, the rows
        of the last call are returned as they are, the directory not even listed, when they reach that time (s).
        """
        known = self._merged_cache.get(bdir)
        if covering_t_s is not None and known is not None and len(known[1]) and known[1][-1, 0] >= covering_t_s:
            return known[1]
        names = _batch_names(bdir)
        if known is not None and names[: len(known[0])] == known[0]:
            fresh = names[len(known[0]) :]
            if not fresh:
                return known[1]
            rows = _appended(known[1], _merge_rows([self._load_batch(bdir / n, kind, width) for n in fresh], width))
        else:
            rows = _merge_rows([self._load_batch(bdir / n, kind, width) for n in names], width)
        if bdir not in self._merged_cache and len(self._merged_cache) >= _MERGED_CACHE_MAX:
            self._merged_cache.pop(next(iter(self._merged_cache)), None)  # the oldest session first
        self._merged_cache[bdir] = (names, rows)
        return rows

    def merged_forces(self, session_id: str, covering_t_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Return (t_s (M,) s strictly increasing, forces_n (M, 4) N as F1..F4) over all batches, deduped.

        covering_t_s: a time (s) the caller needs samples up to; when what this process merged last reaches it, that
        is returned without looking for batches since (a frame's preparation in a long examination: listing 2400
        batches per frame to read two samples cost more than the rest of the merge). Batches arrive in time order;
        one sent late, for times already covered, reaches only the frames prepared after a call that looks (as a
        batch sent after a frame's preparation never reaches that frame live; a reprocess reads every batch).
        """
        bdir = self.session_dir(session_id) / "raw" / "forces"
        rows = self._merged_batches(bdir, "samples", 5, covering_t_s)
        return rows[:, 0].copy(), rows[:, 1:].copy()

    def merged_imu(self, session_id: str, covering_t_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Return (t_s (K,) s strictly increasing, tilt_deg (K, 2) as tilt_x, tilt_y) over all IMU batches
        (covering_t_s as for merged_forces)."""
        bdir = self.session_dir(session_id) / "raw" / "imu"
        rows = self._merged_batches(bdir, "imu", 3, covering_t_s)
        return rows[:, 0].copy(), rows[:, 1:].copy()

    # ----- health ---------------------------------------------------------------------------------------
    def writable(self) -> bool:
        """Return True if a small file can be written durably and removed under data_dir/sessions."""
        probe = self.root / f".probe-{uuid.uuid4().hex}"
        try:
            atomic_write_bytes(probe, b"ok")
            probe.unlink()
            return True
        except OSError:
            return False
