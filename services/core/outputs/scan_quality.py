"""How much of a scan was registered, and the warnings a user must see (issue 6 item 4: never fail silently).

The one owner of the 5 % rule and of the warning texts: the CLI, report.json, GET /v1/sessions/{id} and the
viewer all show what `summarize_frames` and `scan_warnings` return.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

WARN_FRACTION = 0.05  # more than this fraction of frames lost or rejected is a warning
STATUS_OK, STATUS_LOST, STATUS_REJECTED = "ok", "lost", "rejected"
UNKNOWN_REASON = "unknown"  # a lost/rejected row without a reason (older results)
NO_CONTACT = "no_contact"  # rejected: taken in the air between strokes; neither placed nor counted as not placed
WAITING = "unjoined_fragment"  # placed on a fragment that has not joined the map (lost unless it joins)


@dataclass(frozen=True)
class FrameSummary:
    """Counts of a scan's frames by status, and of the not-placed ones by reason (registration.outcome.REASONS)."""

    n_frames: int
    n_ok: int
    n_lost: int
    n_rejected: int
    lost_reasons: Mapping[str, int] = field(default_factory=dict)
    rejected_reasons: Mapping[str, int] = field(default_factory=dict)

    @property
    def n_no_contact(self) -> int:
        """Return the number of frames taken with the window off the skin (rejected, no_contact)."""
        return int(self.rejected_reasons.get(NO_CONTACT, 0))

    @property
    def n_on_skin(self) -> int:
        """Return the number of frames that may have touched the skin: all but those taken in the air."""
        return self.n_frames - self.n_no_contact

    @property
    def n_not_placed(self) -> int:
        """Return the number of frames lost or rejected, those taken in the air apart."""
        return self.n_lost + self.n_rejected - self.n_no_contact

    @property
    def registered_fraction(self) -> float:
        """Return the fraction of the frames on the skin that was placed (0 when there are none)."""
        return self.n_ok / self.n_on_skin if self.n_on_skin else 0.0

    @property
    def not_placed_fraction(self) -> float:
        """Return the fraction of the frames on the skin lost or rejected (0 when there are none)."""
        return self.n_not_placed / self.n_on_skin if self.n_on_skin else 0.0

    @property
    def reasons(self) -> dict[str, int]:
        """Return lost + rejected frames counted per reason (no_contact too), most frequent first."""
        total = Counter(self.lost_reasons) + Counter(self.rejected_reasons)
        return dict(total.most_common())

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form used by report.json, the session state and the viewer."""
        return {
            "total": self.n_frames,
            "ok": self.n_ok,
            "lost": self.n_lost,
            "rejected": self.n_rejected,
            "no_contact": self.n_no_contact,
            "registered_fraction": round(self.registered_fraction, 6),
            "lost_reasons": dict(self.lost_reasons),
            "rejected_reasons": dict(self.rejected_reasons),
        }


def _status_reason(row: Any) -> tuple[str, str]:
    if isinstance(row, Mapping):
        return str(row.get("status") or ""), str(row.get("reason") or "")
    return str(row.status), str(getattr(row, "reason", "") or "")


def summarize_frames(rows: Iterable[Any]) -> FrameSummary:
    """Return the FrameSummary of path rows (PathRow objects or path.json dicts with status and reason)."""
    n = ok = 0
    lost: Counter[str] = Counter()
    rejected: Counter[str] = Counter()
    for row in rows:
        status, reason = _status_reason(row)
        n += 1
        if status == STATUS_OK:
            ok += 1
        elif status == STATUS_REJECTED:
            rejected[reason or UNKNOWN_REASON] += 1
        else:  # lost, or anything not placed
            lost[reason or UNKNOWN_REASON] += 1
    return FrameSummary(
        n_frames=n,
        n_ok=ok,
        n_lost=sum(lost.values()),
        n_rejected=sum(rejected.values()),
        lost_reasons=dict(lost.most_common()),
        rejected_reasons=dict(rejected.most_common()),
    )


def _reasons_text(reasons: Mapping[str, int]) -> str:
    return ", ".join(f"{name.replace('_', ' ')} {count}" for name, count in reasons.items())


def frames_warning(summary: FrameSummary) -> str | None:
    """Return the warning text when more than 5 % of the frames were lost or rejected, else None."""
    if summary.n_on_skin == 0 or summary.not_placed_fraction <= WARN_FRACTION:
        return None
    parts = []
    if summary.n_lost:
        parts.append(f"{summary.n_lost} lost ({_reasons_text(summary.lost_reasons)})")
    rejected = {k: v for k, v in summary.rejected_reasons.items() if k != NO_CONTACT}
    if rejected:
        parts.append(f"{sum(rejected.values())} rejected ({_reasons_text(rejected)})")
    air = f" ({summary.n_no_contact} frames taken off the skin are not counted)" if summary.n_no_contact else ""
    return (
        f"{summary.n_not_placed} of {summary.n_on_skin} frames ({100 * summary.not_placed_fraction:.1f} %) were not "
        f"placed{air}: {'; '.join(parts)}. Only {100 * summary.registered_fraction:.1f} % registered; the path and "
        "the mosaic miss those frames."
    )


LAG_WARNING_S = 5.0  # a live session whose placements trail their uploads by more than this (p95) is behind


@dataclass(frozen=True)
class LiveLag:
    """Upload-to-placement lag of a live session's newest placed frames: median and 95th percentile (s)."""

    p50_s: float
    p95_s: float
    frames: int

    def to_dict(self) -> dict[str, float | int]:
        """Return the JSON form (seconds rounded to 0.01)."""
        return {"p50_s": round(self.p50_s, 2), "p95_s": round(self.p95_s, 2), "frames": self.frames}


def live_lag(lags_s: Sequence[float]) -> LiveLag | None:
    """Return the lag summary of the newest placements' lags (s), or None before any frame was placed."""
    if not lags_s:
        return None
    values = np.asarray(lags_s, float)
    return LiveLag(float(np.percentile(values, 50)), float(np.percentile(values, 95)), len(values))


def scan_warnings(
    summary: FrameSummary | None, status: str = "", reprocessing: bool = False, lag: LiveLag | None = None
) -> list[dict[str, str]]:
    """Return the warnings of a scan or session as [{"code", "message"}]: failed, frames lost, reprocessing,
    and (while it is live) processing more than LAG_WARNING_S behind the uploads."""
    out: list[dict[str, str]] = []
    if status == "failed":
        out.append({"code": "processing_failed", "message": "Processing failed: the results may be incomplete."})
    text = frames_warning(summary) if summary is not None else None
    if text:
        out.append({"code": "frames_lost", "message": text})
    if lag is not None and status in ("receiving", "processing") and lag.p95_s > LAG_WARNING_S:
        out.append(
            {
                "code": "falling_behind",
                "message": f"Processing is behind the uploads: 95 % of the latest frames were placed within "
                f"{lag.p95_s:.1f} s of their upload (more than {LAG_WARNING_S:.0f} s).",
            }
        )
    if reprocessing:
        out.append(
            {
                "code": "reprocess_running",
                "message": "A reprocess is running: the results shown are the previous version until it completes.",
            }
        )
    return out
