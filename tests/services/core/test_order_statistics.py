"""order_statistics.median against numpy's: the same value to the bit, for every dtype a frame comes in."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.core.order_statistics import BRACKET_MIN_SIZE, SAMPLE_SIZE, _bracketed_middle, median


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint8, np.uint16])
def test_median_is_numpys_to_the_bit(dtype: type) -> None:
    # odd and even counts, ties (few distinct values) and a frame's quarter-million pixels; seeded
    rng = np.random.default_rng(7)
    sizes = [1, 2, 3, 4, 5, 10, 11, 255, 256, 287_884]
    for n in sizes:
        for spread in (4, 1000):
            values = (rng.integers(0, spread, n) * (1 / 7 if np.dtype(dtype).kind == "f" else 1)).astype(dtype)
            assert median(values) == float(np.median(values)), (n, spread)
    frame = (rng.random((480, 640)) * (1 if np.dtype(dtype).kind == "f" else 200)).astype(dtype)
    assert median(frame) == float(np.median(frame))  # any shape, read flat


def test_median_leaves_its_input_and_knows_nothing() -> None:
    values = np.array([3.0, 1.0, 2.0, 5.0])
    kept = values.copy()
    assert median(values) == 2.5 and np.array_equal(values, kept)  # partitioned a copy
    assert math.isnan(median(np.array([])))
    assert math.isnan(median(np.array([1.0, np.nan, 2.0])))  # as np.median: NaN anywhere gives NaN


def test_a_large_array_is_bracketed_and_one_that_fools_the_sample_is_partitioned_whole() -> None:
    # a frame's values: the middle found among the few within the sampled bracket, numpy's value to the bit
    rng = np.random.default_rng(11)
    frame = rng.normal(0.5, 0.1, (480, 640)).astype(np.float32)
    assert _bracketed_middle(frame.ravel(), frame.size // 2) is not None
    assert median(frame) == float(np.median(frame))
    # every value the strided sample reads is far above the rest: the bracket misses the middle and the whole
    # array is partitioned, still numpy's value (odd and even counts)
    for n in (BRACKET_MIN_SIZE * 2, BRACKET_MIN_SIZE * 2 + 1):
        fooling = rng.random(n).astype(np.float32)
        fooling[:: n // SAMPLE_SIZE] = 1000.0
        assert _bracketed_middle(fooling, n // 2) is None
        assert median(fooling) == float(np.median(fooling))
