"""
Small array helpers the estimator calls many times on a few dozen numbers.

numpy's general functions pay microseconds of bookkeeping per call that a solve of 20 samples
cannot afford (np.median sorts a copy through several layers; a new random generator costs
more than the draws): these give the same numbers with less of it.
"""

from functools import lru_cache

import numpy as np


def median(values, axis=None):
    """
    Return the median of finite values, as np.median: the middle one, or the mean of two.

    axis None: of all values (a float); an int: along that axis.
    """
    a = np.asarray(values, dtype=float)
    if axis is None:
        a, axis = a.reshape(-1), 0
    n = a.shape[axis]
    if n == 0:
        return np.full(np.delete(a.shape, axis), np.nan)[()] if a.ndim > 1 else float('nan')
    half = n // 2
    if n % 2:
        middle = np.partition(a, half, axis=axis).take(half, axis=axis)
    else:
        part = np.partition(a, (half - 1, half), axis=axis)
        middle = (part.take(half - 1, axis=axis) + part.take(half, axis=axis)) / 2.0
    return float(middle) if np.ndim(middle) == 0 else middle


@lru_cache(maxsize=32)
def random_integers(seed, *draws):
    """
    Return rng.integers(0, high, size) for each (high, size) of `draws`, from one generator.

    rng = np.random.default_rng(seed); the arrays are read-only and remembered.

    The estimator draws with a fixed seed so that the same data give the same answer: the
    draws depend only on the arguments, which repeat from one estimate to the next.
    """
    rng = np.random.default_rng(seed)
    arrays = tuple(rng.integers(0, high, size) for high, size in draws)
    for array in arrays:
        array.flags.writeable = False
    return arrays


def rms(covariance):
    """
    Return sqrt(trace) of a covariance (block): the RMS length of the error it describes.

    A trace below zero (rounding of a nearly singular matrix) counts as zero.
    """
    return float(np.sqrt(max(np.trace(covariance), 0.0)))


def finite_or_none(value):
    """Return `value` as a float, or None (JSON's and YAML's null) when NaN or infinite."""
    value = float(value)
    return value if np.isfinite(value) else None


def inverse(matrix):
    """Return the inverse of a square matrix (or a stack); the pseudo-inverse when singular."""
    try:
        result = np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(matrix)
    return result if np.all(np.isfinite(result)) else np.linalg.pinv(matrix)
