"""The in-memory form of a scan (spec §3): calibration, frame table, force and IMU streams, frames."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.core.inputs.calibration import Calibration


@dataclass(frozen=True)
class Scan:
    """A scan: frames are fetched through `frame_loader(index)` so a folder need not fit in memory.

    Arrays: frame_seq (N,) int, increasing (a gap where the camera dropped a frame), frame_t_s (N,) s,
    force_t_s (M,) s, forces_n (M, 4) N as F1..F4, imu_t_s (K,) s and imu_tilt_deg (K, 2) as (tilt_x, tilt_y)
    deg or None, mask (H, W) uint8 0/255 or None,
    reference_mm (N, 2) in frame 0's coordinates (mm) with NaN rows where unknown, or None;
    reference_angles_deg (N, 3) yaw, tilt_x, tilt_y (deg, spec §4) where the reference has them, or None.
    """

    calibration: Calibration
    frame_seq: np.ndarray
    frame_t_s: np.ndarray
    force_t_s: np.ndarray
    forces_n: np.ndarray
    frame_loader: Callable[[int], np.ndarray]
    mask: np.ndarray | None = None
    imu_t_s: np.ndarray | None = None
    imu_tilt_deg: np.ndarray | None = None
    reference_mm: np.ndarray | None = None
    reference_angles_deg: np.ndarray | None = None
    truth: dict[str, Any] = field(default_factory=dict)

    @property
    def reference_track(self) -> np.ndarray | None:
        """Return the reference track (N, 2) mm, or (N, 5) with yaw and tilts in degrees when known, or None."""
        if self.reference_mm is None or self.reference_angles_deg is None:
            return self.reference_mm
        return np.hstack([self.reference_mm, self.reference_angles_deg])

    def __len__(self) -> int:
        return len(self.frame_seq)

    @property
    def n_seqs(self) -> int:
        """Return the number of seqs from 0 to the last frame's: the path's rows, dropped frames included."""
        return int(self.frame_seq[-1]) + 1 if len(self.frame_seq) else 0

    def by_seq(self, values: np.ndarray | None) -> np.ndarray | None:
        """Return per-frame rows (N, k) spread over seqs 0..n_seqs-1 (n_seqs, k), NaN rows for dropped seqs."""
        if values is None:
            return None
        rows = np.asarray(values, np.float64)
        out = np.full((self.n_seqs, *rows.shape[1:]), np.nan)
        out[np.asarray(self.frame_seq, np.int64)] = rows
        return out

    def frame(self, index: int) -> np.ndarray:
        """Return frame `index` (position in frame_seq, not seq) as a 2-D uint8 or uint16 array."""
        return self.frame_loader(index)


def in_memory_loader(frames: Sequence[np.ndarray]) -> Callable[[int], np.ndarray]:
    """Return a frame_loader over a list of arrays already in memory."""
    frames = list(frames)
    return lambda index: frames[index]
