"""state.json of a results version: the one shape every producer writes and every reader gets back.

    {"format": 1, "cursor": n, "fence": token, "finished": bool, "failed": bool, "lost": [seq], "rejected": [seq]}

cursor: registration has handled frames [0, cursor); fence: the lease token of the last writer (a holder with
an older token must not write); finished: the version is complete; failed: it never will be (a failed
reprocess); lost / rejected: the seqs registered as lost or rejected (replayed as such after a take-over).
A document without "format" was written before formats were recorded (format 0, the same fields).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from services.store.file_formats import check_format

STATE_FORMAT = 1
READABLE_FORMATS = (0, 1)


def _seqs(values: Iterable[Any]) -> tuple[int, ...]:
    return tuple(int(s) for s in values)


@dataclass(frozen=True)
class VersionState:
    """How far a results version got: its registration cursor, fence token, finished or failed, lost and rejected."""

    cursor: int = 0
    fence: int = 0
    finished: bool = False
    failed: bool = False
    lost: tuple[int, ...] = ()
    rejected: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "lost", _seqs(self.lost))  # any iterable of seqs in, a tuple of ints kept
        object.__setattr__(self, "rejected", _seqs(self.rejected))

    def to_json(self) -> dict[str, Any]:
        """Return the state.json document (format STATE_FORMAT)."""
        return {
            "format": STATE_FORMAT,
            "cursor": int(self.cursor),
            "fence": int(self.fence),
            "finished": bool(self.finished),
            "failed": bool(self.failed),
            "lost": list(self.lost),
            "rejected": list(self.rejected),
        }

    @classmethod
    def from_json(cls, doc: Mapping[str, Any], what: str = "state.json") -> VersionState:
        """Return the state of a state.json document; UnknownFormatError (naming `what`) for an unknown format."""
        check_format(what, doc.get("format", 0), READABLE_FORMATS)
        return cls(
            cursor=int(doc.get("cursor", 0)),
            fence=int(doc.get("fence", 0)),
            finished=bool(doc.get("finished", False)),
            failed=bool(doc.get("failed", False)),
            lost=doc.get("lost", ()),
            rejected=doc.get("rejected", ()),
        )
