"""The reference track of spec §4 (reference.csv): the one parser, for scan folders and the service alike.

A reference names each frame's centre (seq, x_mm, y_mm in frame 0's coordinates) and, as a 6-DoF optical
tracker gives them, optionally its yaw relative to frame 0 and the probe's tilts (yaw_deg, tilt_x_deg,
tilt_y_deg: the spec §2 angles). The track is an (N, 5) array aligned to the frame seqs it was parsed for,
columns REFERENCE_COLUMNS, NaN where a frame has no row or the file has no angle columns.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence

import numpy as np

POSITION_HEADER = ("seq", "x_mm", "y_mm")
POSE_HEADER = (*POSITION_HEADER, "yaw_deg", "tilt_x_deg", "tilt_y_deg")
REFERENCE_COLUMNS = POSE_HEADER[1:]  # the track's columns: x_mm, y_mm, yaw_deg, tilt_x_deg, tilt_y_deg


class ReferenceFormatError(ValueError):
    """A reference.csv that does not follow spec §4; the message names the line (never a value of patient data)."""

    def __init__(self, line: int | None, message: str) -> None:
        self.line = line
        self.message = message
        super().__init__(f"reference.csv line {line}: {message}" if line is not None else f"reference.csv: {message}")


def parse_reference_csv(text: str, seqs: Sequence[int]) -> np.ndarray:
    """Return the reference track (len(seqs), 5): mm and degrees per REFERENCE_COLUMNS, aligned to `seqs`.

    Either header of spec §4 is read (positions only, or positions with yaw and tilts); rows may come in any
    order; NaN where a seq has no row. Raises ReferenceFormatError naming the line for a wrong header, a
    non-number or non-finite value, a seq that is not a frame, or a repeated seq.
    """
    index = {int(s): i for i, s in enumerate(seqs)}
    out = np.full((len(index), len(REFERENCE_COLUMNS)), np.nan)
    lines = text.lstrip("\ufeff").splitlines()
    header = tuple(c.strip() for c in lines[0].split(",")) if lines else ()
    if header not in (POSITION_HEADER, POSE_HEADER):
        raise ReferenceFormatError(1, f"expected the header {','.join(POSITION_HEADER)} or {','.join(POSE_HEADER)}")
    width = len(header)
    seen: dict[int, int] = {}
    for lineno, cells in enumerate(csv.reader(lines[1:]), start=2):
        if not cells or not "".join(cells).strip():
            continue
        if len(cells) != width:
            raise ReferenceFormatError(lineno, f"expected {width} values ({','.join(header)}), got {len(cells)}")
        try:
            seq = int(cells[0].strip())
            values = [float(c) for c in cells[1:]]
        except ValueError:
            raise ReferenceFormatError(lineno, "seq must be an integer and the other columns numbers") from None
        if not all(math.isfinite(v) for v in values):
            raise ReferenceFormatError(lineno, f"{', '.join(header[1:])} must be finite")
        if seq not in index:
            raise ReferenceFormatError(lineno, f"seq {seq} is not a frame of this scan")
        if seq in seen:
            raise ReferenceFormatError(lineno, f"seq {seq} repeats line {seen[seq]}")
        seen[seq] = lineno
        out[index[seq], : width - 1] = values
    return out


def reference_csv(seqs: Sequence[int], track: np.ndarray) -> str:
    """Return reference.csv text of a track (N, 2) or (N, 5) aligned to seqs (angles only when all are known)."""
    track = np.asarray(track, dtype=np.float64).reshape(len(seqs), -1)
    placed = np.isfinite(track[:, :2]).all(axis=1)
    with_angles = track.shape[1] == len(REFERENCE_COLUMNS) and bool(np.isfinite(track[placed]).all())
    header = POSE_HEADER if with_angles else POSITION_HEADER
    lines = [",".join(header)]
    for seq, row in zip(seqs, track, strict=True):
        if np.isfinite(row[:2]).all():
            lines.append(",".join([str(int(seq)), *(repr(float(v)) for v in row[: len(header) - 1])]))
    return "\n".join(lines) + "\n"
