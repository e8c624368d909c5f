"""A 95% interval for the mean of a few independent runs (seeds), by Student's t.

Episode-level intervals (`EvalResult.ci95`) average thousands of episodes, where 1.96 standard errors
is right; over 5 seeds it is not (t = 2.78 for 4 degrees of freedom), so results over seeds use this.
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


def mean_interval(values: ArrayLike, axis: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, low, high) over `axis` (the seeds); a single run gives low = high = mean."""
    x = np.asarray(values, dtype=np.float64)
    n = x.shape[axis]
    mean = x.mean(axis=axis)
    if n < 2:
        return mean, mean.copy(), mean.copy()
    half = t975(n - 1) * x.std(axis=axis, ddof=1) / math.sqrt(n)
    return mean, mean - half, mean + half
