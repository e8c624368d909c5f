"""A 95% interval for a mean, by Student's t: over a few runs (seeds) and over a policy's episodes alike.

Over thousands of episodes t is 1.96 to three digits, but `bitcomm eval --episodes 5` and a study's 5 seeds
are not thousands (t = 2.78 for 4 degrees of freedom), so every interval uses t. Where the values have a
possible range (an episode lasts 1 to max_steps steps), the interval is cut to it: the mean cannot leave
it, and a normal approximation over a few values can. One value has no spread to measure: its interval is
the whole range where there is one, else the value itself (tables print no interval for one seed).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
        2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
        2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)  # fmt: skip
"""The 0.975 quantile of Student's t with 1..30 degrees of freedom."""


def t975(df: int) -> float:
    """Student's t 0.975 quantile; past the table, 1.96 + 2.37 / df (Cornish-Fisher, within 0.003)."""
    if df < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    return T975[df - 1] if df <= len(T975) else 1.96 + 2.37 / df


def mean_interval(
    values: ArrayLike, axis: int = 0, bounds: tuple[float, float] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, low, high) over `axis` (the seeds, or the episodes), cut to `bounds` (the values' possible range)
    where given; a single value gives the whole of `bounds`, or low = high = mean without them."""
    x = np.asarray(values, dtype=np.float64)
    n = x.shape[axis]
    mean = x.mean(axis=axis)
    if n < 2:
        if bounds is None:
            return mean, mean.copy(), mean.copy()
        return mean, np.full_like(mean, bounds[0]), np.full_like(mean, bounds[1])
    half = t975(n - 1) * x.std(axis=axis, ddof=1) / math.sqrt(n)
    low, high = mean - half, mean + half
    if bounds is not None:
        low, high = np.maximum(low, bounds[0]), np.minimum(high, bounds[1])
    return mean, low, high
