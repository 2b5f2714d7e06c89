"""Contact decisions: the load against the learned tare, the image's focus against skin in contact."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.core.contact import ContactDetector, focus_measure
from tests.shared_scans import SHARED_CLINICAL, clinical_until


def _veins(seed: int) -> np.ndarray:
    """Return a 240 x 320 skin-like frame: smooth grey with thin dark lines (veins)."""
    rng = np.random.default_rng(seed)
    img = np.full((240, 320), 150, np.uint8)
    for _ in range(12):
        p, q = rng.integers(0, 320, 2), rng.integers(0, 240, 2)
        cv2.line(img, (int(p[0]), int(q[0])), (int(p[1]), int(q[1])), 110, 2)
    return cv2.GaussianBlur(img, (0, 0), 0.8)


def test_focus_is_high_for_skin_in_focus_and_low_for_the_same_skin_defocused() -> None:
    mask = np.full((240, 320), 255, np.uint8)
    sharp = _veins(1)
    blurred = cv2.GaussianBlur(sharp, (0, 0), 4.0)
    assert focus_measure(sharp, mask) > 2 * focus_measure(blurred, mask)
    # the measure divides by the window's median grey: a darker exposure of the same skin reads the same focus
    darker = (sharp.astype(np.float32) * 0.5).astype(np.uint8)
    assert focus_measure(darker, mask) == pytest.approx(focus_measure(sharp, mask), rel=0.1)


def _learned(detector: ContactDetector, frames: int = 12) -> None:
    """Feed a detector a stroke in contact (8 N, focus 1.0) then a lift in the air (0.06 N, focus 0.4)."""
    for _ in range(frames):
        assert detector.decide(8.0, 1.0).contact
    for k in range(frames):
        assert not detector.decide(0.06 + 0.01 * (k % 3), 0.4).contact


def test_the_tare_is_learned_from_the_air_and_a_light_landing_counts() -> None:
    detector = ContactDetector()
    _learned(detector)
    assert detector.tare_n == pytest.approx(0.07, abs=0.01)
    # 0.3 N above nothing is contact by the load (the sensors' noise is ~0.01 N here)
    decision = detector.decide(0.37, float("nan"))
    assert decision.contact and decision.by == "load"


def test_the_image_overrules_the_load_at_a_landing_and_a_lift_the_force_clock_has_not_seen() -> None:
    detector = ContactDetector()
    _learned(detector)
    landing = detector.decide(0.1, 1.05)  # a trace of load, and the skin in focus: the force log lags
    assert landing.contact and landing.by == "image"
    assert not detector.decide(0.07, 1.05).contact  # in focus but no load at all: the image alone does not decide
    lift = detector.decide(0.8, 0.3)  # a load still, but the image is as blurred as the air
    assert not lift.contact and lift.by == "image"
    # a clear load with a blurred image is motion blur on the skin, not the air
    assert detector.decide(6.0, 0.3).contact


@pytest.mark.skipif(not SHARED_CLINICAL.is_dir(), reason="the shared reference scans are not on this machine")
def test_on_the_clinical_scan_every_frame_is_decided_as_the_tracker_says() -> None:
    # reference.csv has a row for every frame that touched the skin and none for frames in the air
    from services.core.methods import method_options
    from services.core.pipeline import frame_forces, prepared_frames, window_setup

    scan = clinical_until(130)
    options = method_options("best")
    mask, flat = window_setup(scan, options)
    touched = {int(s) for s, r in zip(scan.frame_seq, scan.reference_mm, strict=True) if np.isfinite(r).all()}
    detector = ContactDetector()
    decided = {pf.seq: detector.decide(pf.load.fz_n, pf.focus).contact for pf in
               prepared_frames(scan, frame_forces(scan), mask, flat, options)}  # fmt: skip
    assert {s for s, c in decided.items() if c} == touched
    assert len(decided) - len(touched) >= 20  # the lifts after rows 1 and 2 are in this part
