"""Send DICOM objects to one PACS destination: the one entry point (STOW-RS or C-STORE by destination kind).

    outcome = send_objects(settings.pacs_destinations["hospital"], [dcm_bytes, ...], settings.pacs_timeout_s)

Returns a SendOutcome when the PACS stored every instance, or some of them (`outcome.failed` names the refused
ones with a reason); raises PacsUnreachable (worth retrying: re-sending stores the same instances) or
PacsRejected (the PACS refused: nothing stored, or the request refused as a whole). ValueError when an object
is not usable DICOM Part 10 (nothing is sent then).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from services.pacs.cstore import c_store
from services.pacs.destinations import DicomWebDestination, DimseDestination
from services.pacs.objects import read_objects
from services.pacs.outcome import PacsError, PacsRejected, PacsUnreachable, SendOutcome
from services.pacs.stow import stow

__all__ = ["PacsError", "PacsRejected", "PacsUnreachable", "SendOutcome", "send_objects"]

log = logging.getLogger("veinmosaic.pacs")


def send_objects(
    destination: DicomWebDestination | DimseDestination, objects: Sequence[bytes], timeout_s: float
) -> SendOutcome:
    """Return the outcome of storing Part 10 `objects` at `destination` (timeout per network step; see module doc)."""
    if timeout_s <= 0:
        raise ValueError(f"timeout_s must be positive, got {timeout_s!r}")
    items = read_objects(objects)
    if not items:
        return SendOutcome(destination.describe(), ())
    try:
        if isinstance(destination, DicomWebDestination):
            outcome = stow(destination, items, timeout_s)
        elif isinstance(destination, DimseDestination):
            outcome = c_store(destination, items, timeout_s)
        else:
            raise TypeError(f"not a PACS destination: {type(destination).__name__}")
    except PacsError as exc:
        log.warning("PACS send failed: %s", exc)  # messages carry UIDs and status codes only
        raise
    log.info(
        "PACS send: %d stored, %d refused at %s in %.1f s",
        outcome.sent,
        len(outcome.failed),
        outcome.destination,
        outcome.elapsed_s,
    )
    return outcome
