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


def npz_bytes(**arrays: np.ndarray) -> bytes:
    """Return arrays as .npz bytes (np.load reads them), deflated at NPZ_COMPRESS_LEVEL."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=NPZ_COMPRESS_LEVEL) as archive:
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as entry:
                np.lib.format.write_array(entry, np.asanyarray(value), allow_pickle=False)
    return buf.getvalue()
