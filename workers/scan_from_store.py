"""A Scan (services.core.inputs.scan) over a session's stored raw uploads, for reprocessing offline."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from services.core.inputs.calibration import Calibration
from services.core.inputs.scan import Scan
from services.store.storage import SessionStore


def stored_forces(store: SessionStore, session_id: str, first_t_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Return (t_s (M,), forces (M, 4) N) merged over all batches; one zero sample when none were sent.

    Without force data the frames are treated as unloaded (no rectification), the same live and offline.
    """
    t, f = store.merged_forces(session_id)
    if len(t) == 0:
        return np.array([float(first_t_s)]), np.zeros((1, 4))
    return t, f


def scan_from_store(
    store: SessionStore,
    session_id: str,
    calibration: Calibration | None = None,
    exclude_seqs: Iterable[int] = (),
) -> Scan:
    """Return the session's stored frames (sorted by seq, minus exclude_seqs), forces and IMU as a Scan."""
    skip = {int(s) for s in exclude_seqs}
    records = [rec for rec in store.list_frames(session_id) if rec.seq not in skip]
    if not records:
        raise ValueError("the session has no frames to process")
    seqs = np.array([rec.seq for rec in records], np.int64)
    times = np.array([rec.t_s for rec in records], np.float64)
    force_t, forces = stored_forces(store, session_id, float(times[0]))
    imu_t, imu = store.merged_imu(session_id)

    def loader(index: int) -> np.ndarray:
        return store.load_frame(session_id, int(seqs[index]))

    return Scan(
        calibration=calibration if calibration is not None else store.calibration(session_id),
        frame_seq=seqs,
        frame_t_s=times,
        force_t_s=force_t,
        forces_n=forces,
        frame_loader=loader,
        mask=None,
        imu_t_s=imu_t if len(imu_t) else None,
        imu_tilt_deg=imu if len(imu_t) else None,
    )
