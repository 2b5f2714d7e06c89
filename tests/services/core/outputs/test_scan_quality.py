"""The one owner of the 5 % rule and the warning texts (issue 6 item 4: never fail silently)."""

from __future__ import annotations

import math

import pytest

from services.core.outputs.scan_quality import WARN_FRACTION, frames_warning, scan_warnings, summarize_frames
from services.core.path_rows import PathRow


def _rows(n: int, lost: dict[int, str], rejected: dict[int, str] | None = None) -> list[PathRow]:
    rejected = rejected or {}
    out = []
    for seq in range(n):
        status = "lost" if seq in lost else "rejected" if seq in rejected else "ok"
        reason = lost.get(seq) or rejected.get(seq) or ""
        out.append(PathRow(seq, 0.1 * seq, math.nan, math.nan, math.nan, 5.0, 0.0, 0.0, 1.0, 0, status, reason))
    return out


def test_counts_per_status_and_reason() -> None:
    rows = _rows(40, {3: "few_inliers", 4: "few_inliers", 9: "missing"}, {12: "blur"})
    s = summarize_frames(rows)
    assert (s.n_frames, s.n_ok, s.n_lost, s.n_rejected) == (40, 36, 3, 1)
    assert s.lost_reasons == {"few_inliers": 2, "missing": 1} and s.rejected_reasons == {"blur": 1}
    assert s.reasons == {"few_inliers": 2, "missing": 1, "blur": 1}
    assert s.registered_fraction == 36 / 40
    # the same from path.json dicts
    dicts = [{"status": r.status, "reason": r.reason} for r in rows]
    assert summarize_frames(dicts) == s


def test_five_percent_rule_boundary() -> None:
    assert WARN_FRACTION == 0.05
    assert frames_warning(summarize_frames(_rows(100, {i: "few_inliers" for i in range(5)}))) is None  # 5 %: not more
    text = frames_warning(summarize_frames(_rows(100, {i: "few_inliers" for i in range(6)})))
    assert text is not None and text.startswith("6 of 100 frames (6.0 %) were not placed")
    assert "few inliers 6" in text and "94.0 % registered" in text


def test_rejected_count_toward_the_rule_and_old_rows_without_reason() -> None:
    rows = _rows(20, {1: ""}, {2: "implausible_jump"})
    text = frames_warning(summarize_frames(rows))
    assert text is not None and "1 lost (unknown 1)" in text and "1 rejected (implausible jump 1)" in text


def test_session_warnings_failed_and_reprocess() -> None:
    ok = summarize_frames(_rows(10, {}))
    assert scan_warnings(ok) == []
    codes = [w["code"] for w in scan_warnings(summarize_frames(_rows(10, {0: "missing"})), "failed", True)]
    assert codes == ["processing_failed", "frames_lost", "reprocess_running"]
    assert scan_warnings(None, "done") == []
    assert summarize_frames([]).registered_fraction == 0.0 and frames_warning(summarize_frames([])) is None


def test_live_lag_summary_and_warning() -> None:
    from services.core.outputs.scan_quality import LAG_WARNING_S, live_lag, scan_warnings

    assert live_lag([]) is None
    lag = live_lag([1.0, 2.0, 3.0, 4.0, 10.0])
    assert lag is not None and lag.p50_s == 3.0 and lag.frames == 5
    assert lag.p95_s == pytest.approx(8.8)  # linear interpolation between 4 and 10 (tolerance: float rounding)
    codes = [w["code"] for w in scan_warnings(None, "processing", lag=lag)]
    assert codes == ["falling_behind"] and lag.p95_s > LAG_WARNING_S
    assert scan_warnings(None, "done", lag=lag) == []  # a finished session is not behind
    assert scan_warnings(None, "processing", lag=live_lag([1.0, 2.0])) == []
