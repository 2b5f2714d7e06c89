"""The force clock's offset, fitted to the frames' stretches against their loads and load rates."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.physics.force_clock import estimate_clock_offset, load_rates

# the stretches' noise below is 1e-4 (a pose scale's, on the shared scans); over 200 frames of loads changing at
# ~10 N/s that pins a 30 ms offset to a few ms: 5 ms fails a wrong sign or a unit slip (s vs ms) with margin
OFFSET_TOL_S = 0.005


def _frames(offset_s: float, seed: int = 1) -> tuple[np.ndarray, ...]:
    """Return (stretches, frame times s, logged loads N, runs) of two strokes whose logger runs offset_s off."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([np.arange(100) * 0.1, 15.0 + np.arange(100) * 0.1])
    run = np.repeat([0, 1], 100)

    def true_load(when: np.ndarray) -> np.ndarray:
        return 9.0 + 7.0 * np.sin(1.3 * when) + 2.0 * np.sin(3.1 * when + 1.0)

    logged = true_load(t - offset_s)  # the logger stamps the load at t with t + offset
    stretch = 1.0 + 0.003 * true_load(t) + rng.normal(0.0, 1e-4, len(t))
    return stretch, t, logged, run


@pytest.mark.parametrize("offset_s", [-0.04, 0.0, 0.03])
def test_the_offset_is_recovered(offset_s: float) -> None:
    found = estimate_clock_offset(*_frames(offset_s))
    assert found is not None and found.frames == 196  # a rate needs both neighbours in the run
    assert found.offset_s == pytest.approx(offset_s, abs=OFFSET_TOL_S)
    assert found.standard_error_s < OFFSET_TOL_S


def test_no_rate_across_a_lift_and_no_estimate_without_load_dependence() -> None:
    rates = load_rates(np.array([0.0, 0.1, 0.2, 0.3]), np.array([1.0, 2.0, 3.0, 4.0]), np.array([0, 0, 1, 1]))
    assert np.isnan(rates).all()  # frames 1 and 2 each have a neighbour in the other run
    stretch, t, logged, run = _frames(0.03)
    assert estimate_clock_offset(np.full_like(stretch, 1.0), t, logged, run) is None  # nothing to time
    assert estimate_clock_offset(stretch[:10], t[:10], logged[:10], run[:10]) is None  # too few frames
