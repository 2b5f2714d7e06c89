"""Format versions of the files a results version keeps (prepared frames, state.json); their npz encoding is
services.core.npz.

Every such file records the format it was written in; a reader accepts the formats it knows and refuses any
other with UnknownFormatError, naming the file and the formats it reads (as OpenSfM versions its feature
files). A file written before formats were recorded reads as format 0: the same layout as format 1.
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

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
