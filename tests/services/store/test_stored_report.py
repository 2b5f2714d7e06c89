"""When the API rebuilds a stored report.json (services/store/stored_report.report_is_stale)."""

from __future__ import annotations

from services.store.stored_report import report_is_stale

CURRENT = {"mosaic_version": 7, "rmse_mm": 0.2, "global_error": {"scale_pct": 0.1}}


def test_a_report_of_the_current_mosaic_is_served_as_stored() -> None:
    assert not report_is_stale(CURRENT, {"version": 7})


def test_a_missing_report_or_one_of_another_mosaic_version_is_rebuilt() -> None:
    assert report_is_stale(None, {"version": 7})
    assert report_is_stale(CURRENT, {"version": 8})
    assert report_is_stale({k: v for k, v in CURRENT.items() if k != "mosaic_version"}, {"version": 7})


def test_a_report_written_before_global_error_existed_is_rebuilt() -> None:
    older = {k: v for k, v in CURRENT.items() if k != "global_error"}
    assert report_is_stale(older, {"version": 7})
