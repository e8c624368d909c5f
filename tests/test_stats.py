"""A 95% interval over seeds by Student's t, against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bitcomm.studies.stats import mean_interval, t975


def test_t_quantiles() -> None:
    assert t975(1) == 12.706 and t975(4) == 2.776 and t975(30) == 2.042
    assert abs(t975(60) - 2.000) < 0.003 and abs(t975(10_000) - 1.960) < 0.001
    with pytest.raises(ValueError):
        t975(0)


def test_mean_interval_by_hand() -> None:
    mean, lo, hi = mean_interval([1.0, 2.0, 3.0])  # sd 1, n 3: half-width 4.303 / sqrt(3)
    assert mean == 2.0 and math.isclose(hi - mean, 4.303 / math.sqrt(3)) and math.isclose(mean - lo, hi - mean)
    curves = np.array([[1.0, 10.0], [3.0, 10.0]])  # seeds x grid points
    mean, lo, hi = mean_interval(curves)
    assert np.allclose(mean, [2.0, 10.0]) and np.allclose(hi - mean, [12.706, 0.0])  # sd sqrt(2), n 2
    assert mean_interval([4.0]) == (4.0, 4.0, 4.0)
