"""Order statistics of a frame's pixels, as numpy computes them but with less work.

`np.median` of an even count partitions about both middle positions; one partition about the upper one and the
largest value below it give the same two values, and the same mean of them. On a frame's quarter-million pixels
(normalise_photometry and contact.focus_measure take one per frame) even one partition costs milliseconds, so a
large array is first bracketed: a strided sample's quantiles a few standard errors either side of the middle give
bounds lo <= hi, the values below lo are counted, and when the middle positions fall among the values within
[lo, hi] (a few per cent of them) only those are partitioned. When they do not (a sample that misjudged the
array's order), the whole array is partitioned as before: the value is numpy's either way.
"""

from __future__ import annotations

import numpy as np

BRACKET_MIN_SIZE = 65_536  # smaller arrays are partitioned whole (the bracket's passes would cost more)
SAMPLE_SIZE = 16_384  # about this many values, strided, estimate the bracket
BRACKET_SIGMAS = 6.0  # the bracket spans this many of the sample median's standard errors either side


def median(values: np.ndarray) -> float:
    """Return the median of `values` (any shape, read flat), equal to float(np.median(values)); NaN if empty or
    any value is NaN, as np.median."""
    flat = np.asarray(values).ravel()
    n = flat.size
    if n == 0 or (flat.dtype.kind == "f" and np.isnan(flat).any()):
        return float(np.median(flat)) if n else float("nan")
    k = n // 2
    middle = _bracketed_middle(flat, k) if n >= BRACKET_MIN_SIZE else None
    if middle is None:
        part = np.partition(flat, k)  # a copy: values left as they were
        middle = (part[:k].max() if n % 2 == 0 else part[k], part[k])
    if n % 2:
        return float(middle[1])
    # np.median's mean of the two middle values, in the array's own dtype (float32 stays float32)
    return float(np.mean(np.array(middle, dtype=flat.dtype)))


def _bracketed_middle(flat: np.ndarray, k: int) -> tuple[np.generic, np.generic] | None:
    """Return the values at sorted positions k - 1 and k of flat (n >= 2) found among those within a sampled
    bracket about the middle, or None when the bracket does not hold both positions."""
    n = flat.size
    sample = flat[:: max(1, n // SAMPLE_SIZE)]
    m = sample.size
    reach = int(np.ceil(BRACKET_SIGMAS * 0.5 * np.sqrt(m)))  # the sample median's standard error is sqrt(m) / 2
    at = (max(0, m // 2 - reach), min(m - 1, m // 2 + reach))
    lo, hi = np.partition(sample, at)[list(at)]
    below = int(np.count_nonzero(flat < lo))
    inside = flat[(flat >= lo) & (flat <= hi)]
    first, last = k - 1 - below, k - below  # positions k - 1 and k among the values inside the bracket
    if first < 0 or last >= inside.size:
        return None
    part = np.partition(inside, (first, last))
    return part[first], part[last]
