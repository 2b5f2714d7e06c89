"""Format versions of the files a results version keeps (prepared frames, state.json), and their npz encoding.

Every such file records the format it was written in; a reader accepts the formats it knows and refuses any
other with UnknownFormatError, naming the file and the formats it reads (as OpenSfM versions its feature
files). A file written before formats were recorded reads as format 0: the same layout as format 1.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Collection

import numpy as np

NPZ_COMPRESS_LEVEL = 1  # deflate level of prepared frames: level 6 (numpy's) cost 33 ms a frame, 1 costs 8 (+7 %)
# A prepared frame's rectified image, vein map and descriptors are stored, not deflated: deflate halved the image
# only (151 of 307 kB) and cost 5.5 of a frame's 7 ms to write and 2 ms to read (a simulated raster frame)
PREPARED_STORED = ("image", "vein", "descriptors")


class UnknownFormatError(ValueError):
    """A results file in a format this release does not read (written by a newer release, or damaged)."""


def check_format(what: str, found: object, readable: Collection[int]) -> int:
    """Return the format `found` of the file `what` when it is one of `readable`; else UnknownFormatError."""
    if isinstance(found, bool) or not isinstance(found, int | np.integer) or int(found) not in readable:
        known = ", ".join(str(f) for f in sorted(readable))
        raise UnknownFormatError(
            f"{what}: format {found!r} is unknown to this release (it reads formats {known}); "
            "it was written by a newer veinmosaic or is damaged"
        )
    return int(found)


def npz_bytes(stored: Collection[str] = (), **arrays: np.ndarray) -> bytes:
    """Return arrays as .npz bytes (np.load reads them), deflated at NPZ_COMPRESS_LEVEL except those named in
    `stored`, kept as they are (arrays that deflate barely shrinks cost more time to deflate than they save)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as archive:
        for name, value in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
            if name in stored:
                archive.writestr(f"{name}.npy", member.getvalue(), compress_type=zipfile.ZIP_STORED)
            else:
                archive.writestr(
                    f"{name}.npy", member.getvalue(), zipfile.ZIP_DEFLATED, compresslevel=NPZ_COMPRESS_LEVEL
                )
    return buf.getvalue()
