"""The estimator's small array helpers give numpy's own numbers."""

import numpy as np
from numpy.testing import assert_array_equal

from quatcal_ros.core.numerics import median, random_integers


def test_median_equals_numpy_for_odd_and_even_counts_and_along_an_axis():
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 10, 11, 190):
        values = rng.normal(size=n)
        assert median(values) == np.median(values)
        table = rng.normal(size=(5, n))
        assert_array_equal(median(table, axis=1), np.median(table, axis=1))
        assert_array_equal(median(table, axis=0), np.median(table, axis=0))
    assert np.isnan(median(np.array([])))


def test_random_integers_are_the_generators_draws_in_turn_and_cannot_be_changed():
    a, b = random_integers(4, (10, 7), (9, 5))
    rng = np.random.default_rng(4)
    assert_array_equal(a, rng.integers(0, 10, 7))
    assert_array_equal(b, rng.integers(0, 9, 5))
    assert random_integers(4, (10, 7), (9, 5))[0] is a     # remembered
    assert not a.flags.writeable
