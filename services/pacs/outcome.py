"""What a send to a PACS comes to: the outcome (stored and refused instances) or one of two errors.

PacsUnreachable: the PACS could not be reached or had a passing fault (refused connection, timeout, HTTP 5xx,
association rejected transiently or aborted): worth retrying, re-sending is idempotent. PacsRejected: the PACS
answered and refused (every instance, or the request as a whole): not worth retrying until someone changes the
objects or the configuration. A per-instance failure status is always a refusal, even "out of resources"
(0xA7xx): Orthanc, for one, answers 0xA700 for any instance it cannot store. Messages name SOP Instance UIDs
and status codes only, never patient data nor response bodies.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

from services.pacs.objects import DicomObject

# DICOM status codes (PS3.7 Annex C, PS3.4 B.2.3, PS3.18 STOW-RS Failure Reason) a PACS answers per instance
_STATUS_NAMES = {
    0x0000: "success",
    0x0107: "warning: attribute list error",
    0x0110: "processing failure",
    0x0116: "warning: attribute value out of range",
    0x0117: "invalid SOP instance",
    0x0122: "SOP class not supported",
    0x0124: "not authorised",
    0x0210: "duplicate invocation",
    0x0211: "unrecognised operation",
    0x0212: "mistyped argument",
    0xB000: "warning: coercion of data elements",
    0xB006: "warning: elements discarded",
    0xB007: "warning: data set does not match SOP class",
    0xC122: "transfer syntax not supported",
}
_STORED_WITH_WARNING = frozenset({0x0107, 0x0116, 0xB000, 0xB006, 0xB007})


def status_text(code: int) -> str:
    """Return 'status 0xA700 (out of resources)' for a DICOM status or failure reason code."""
    if code in _STATUS_NAMES:
        name = _STATUS_NAMES[code]
    elif 0xA700 <= code <= 0xA7FF:
        name = "refused: out of resources"
    elif 0xA900 <= code <= 0xA9FF:
        name = "data set does not match SOP class"
    elif 0xC000 <= code <= 0xCFFF:
        name = "cannot understand"
    else:
        name = "unknown status"
    return f"status 0x{code:04X} ({name})"


def is_stored(code: int) -> bool:
    """Return whether a per-instance status means the PACS stored the instance (success or a warning)."""
    return code == 0x0000 or code in _STORED_WITH_WARNING


@dataclass(frozen=True)
class SendOutcome:
    """Instances the PACS stored, those it refused (reason per SOP Instance UID), where, and how long it took."""

    destination: str  # Destination.describe(): no credentials
    stored: tuple[str, ...]  # SOP Instance UIDs the PACS stored (or already held), in the order given
    failed: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}))  # UID -> reason
    elapsed_s: float = 0.0

    @property
    def sent(self) -> int:
        """Return how many instances the PACS stored."""
        return len(self.stored)

    @property
    def ok(self) -> bool:
        """Return whether every instance was stored."""
        return not self.failed


class PacsError(Exception):
    """A send that did not complete; the message names the destination, never patient data.

    `outcome` is the per-instance result when the PACS gave one (a PacsRejected of every instance), else None.
    """

    def __init__(self, message: str, outcome: SendOutcome | None = None) -> None:
        super().__init__(message)
        self.outcome = outcome


class PacsUnreachable(PacsError):  # noqa: N818  (the names the send job uses)
    """The PACS could not be reached or had a passing fault: worth retrying (re-sending is idempotent)."""


class PacsRejected(PacsError):  # noqa: N818
    """The PACS refused the objects or the request: not worth retrying as is."""


def conclude(
    destination: str,
    objects: Sequence[DicomObject],
    results: Mapping[str, int | str],
    started: float,
) -> SendOutcome:
    """Return the outcome of per-instance results (a status code, or a reason text for a failure), or raise.

    Nothing stored (and something refused) raises PacsRejected; otherwise the outcome, whose `failed` lists
    what the PACS refused when it stored the rest.
    """
    stored: list[str] = []
    failed: dict[str, str] = {}
    for obj in objects:
        uid = obj.sop_instance_uid
        result = results.get(uid, "no status for this instance in the PACS's answer")
        if isinstance(result, int) and is_stored(result):
            stored.append(uid)
        else:
            failed[uid] = status_text(result) if isinstance(result, int) else result
    outcome = SendOutcome(destination, tuple(stored), MappingProxyType(failed), time.monotonic() - started)
    if failed and not stored:
        first = next(iter(failed))
        raise PacsRejected(
            f"{destination}: the PACS stored none of {len(objects)} instance(s), e.g. {first}: {failed[first]}",
            outcome,
        )
    return outcome
