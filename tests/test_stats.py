"""A 95% interval for a mean by Student's t (over seeds or episodes), against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bitcomm.stats import mean_interval, t975


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


def test_an_interval_stays_within_the_range_the_values_can_take() -> None:
    # episodes of 1 and 256 steps: t(1) = 12.706, half-width 12.706 * sd / sqrt(2) = 12.706 * 127.5, far past both ends
    mean, lo, hi = mean_interval([1.0, 256.0], bounds=(1, 256))
    assert (mean, lo, hi) == (128.5, 1.0, 256.0)
    mean, lo, hi = mean_interval([10.0, 11.0, 12.0], bounds=(1, 256))  # a narrow one is left as it is
    assert math.isclose(hi - mean, 4.303 / math.sqrt(3)) and math.isclose(mean - lo, hi - mean)


def test_one_value_in_a_known_range_has_the_whole_range_as_its_interval() -> None:
    assert mean_interval([7.0], bounds=(1, 256)) == (7.0, 1.0, 256.0)
