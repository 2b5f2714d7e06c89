"""A prepared frame's file (<v>/prepared/<seq>.npz): lossless, so registration replays it exactly; versioned.

PREPARED_FORMAT is recorded in the file (array "format"); a file without it is format 0, the same layout.
"""

from __future__ import annotations

import io
import math

import numpy as np

from services.core.npz import npz_bytes, npz_members
from services.core.physics.force_model import LoadState
from services.core.registration.features import Features
from services.core.registration.frame_prep import PreparedFrame
from services.store.file_formats import PREPARED_STORED, check_format

# 2: the IMU's tilts at the frame time (array "imu_tilt_deg", absent without an IMU); 3: the focus measure
# (array "focus"; NaN, unknown, when read from an older file); 4: the features optional (no "points": none yet)
PREPARED_FORMAT = 4
READABLE_FORMATS = (0, 1, 2, 3, 4)


def prepared_to_bytes(pf: PreparedFrame) -> bytes:
    """Return a PreparedFrame as .npz bytes (lossless; descriptors as uint8 when they are whole 0..255)."""
    imu = {} if pf.imu_tilt_deg is None else {"imu_tilt_deg": np.asarray(pf.imu_tilt_deg, np.float64)}
    return npz_bytes(
        PREPARED_STORED,
        **imu,
        **_features_arrays(pf.features),
        format=np.array([PREPARED_FORMAT], np.int64),
        meta=np.array([pf.index, pf.seq], np.int64),
        scalars=np.array(
            [pf.t_s, pf.load.fz_n, pf.load.theta_x_rad, pf.load.theta_y_rad, pf.stretch, pf.sharpness], np.float64
        ),
        forces_n=np.asarray(pf.forces_n, np.float64),
        image=pf.image,
        mask=pf.mask,
        vein=pf.vein,
        vein_mask=pf.vein_mask,
        focus=np.array([pf.focus], np.float64),
    )


def _features_arrays(features: Features | None) -> dict[str, np.ndarray]:
    """Return a frame's features as the file's arrays (none for a frame not described yet: format 4)."""
    if features is None:
        return {}
    desc = np.asarray(features.descriptors)
    if desc.size == 0 or (
        np.all(np.isfinite(desc)) and desc.min() >= 0 and desc.max() <= 255 and np.array_equal(desc, np.round(desc))
    ):
        desc_stored = desc.astype(np.uint8)
    else:
        desc_stored = desc.astype(np.float32)
    return {
        "desc_float": np.array([desc.dtype == np.float32], bool),
        "points": np.asarray(features.points, np.float64),
        "descriptors": desc_stored,
        "desc_width": np.array([desc.shape[1] if desc.ndim == 2 else 128], np.int64),
        "sizes_px": np.asarray(features.sizes_px, np.float64),
    }


def prepared_from_bytes(data: bytes, what: str = "prepared frame") -> PreparedFrame:
    """Return the PreparedFrame stored by `prepared_to_bytes`; UnknownFormatError naming `what` if unknown."""
    z = np.load(io.BytesIO(data), allow_pickle=False)
    check_format(what, int(z["format"][0]) if "format" in z.files else 0, READABLE_FORMATS)
    index, seq = (int(v) for v in z["meta"])
    t_s, fz, tx, ty, stretch, sharpness = (float(v) for v in z["scalars"])
    features = None  # a frame prepared for tracking is described by registration if it becomes a keyframe
    if "points" in z.files:
        # whole 0..255 descriptors stay uint8, as features.detect makes them: a live session keeps every frame's
        # features, and float32 would hold 4x the memory for the same values
        desc = z["descriptors"].reshape(-1, int(z["desc_width"][0]))
        desc = desc.astype(np.float32) if bool(z["desc_float"][0]) else desc.astype(np.uint8)
        features = Features(z["points"].reshape(-1, 2), desc, z["sizes_px"])
    return PreparedFrame(
        index=index,
        seq=seq,
        t_s=t_s,
        forces_n=z["forces_n"],
        load=LoadState(fz, tx, ty),
        stretch=stretch,
        image=z["image"],
        mask=z["mask"],
        features=features,
        vein=z["vein"],
        vein_mask=z["vein_mask"],
        sharpness=sharpness,
        imu_tilt_deg=z["imu_tilt_deg"] if "imu_tilt_deg" in z.files else None,
        focus=float(z["focus"][0]) if "focus" in z.files else math.nan,
    )


def prepared_pixels_from_bytes(data: bytes, what: str = "prepared frame") -> tuple[np.ndarray, np.ndarray]:
    """Return only the rectified image and window mask (H, W) uint8 of a `prepared_to_bytes` file, read-only (the
    rest is not read; KeyError if either is missing).

    Read from the members' local headers (npz_members): a finish reads every frame's pixels back, and opening the
    archive cost twice the reading.
    """
    members = npz_members(data, ("format", "image", "mask"))
    check_format(what, int(members["format"][0]) if "format" in members else 0, READABLE_FORMATS)
    return members["image"], members["mask"]
