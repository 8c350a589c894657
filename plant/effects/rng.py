"""Counter-based noise: reproducible, allocation-free, one stream per axis.

A draw is a pure function of (seed, counter), so the sequence does not depend
on other axes or on numba's global generator; the counter lives in the state.
"""

import math

import numpy as np
from numba import njit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


@njit(cache=True, error_model="numpy")
def splitmix64(x):
    """The splitmix64 finaliser of ``x`` (uint64)."""
    z = x + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@njit(cache=True, error_model="numpy")
def uniform(seed, counter):
    """Uniform number in (0, 1) for draw ``counter`` (both whole numbers as floats)."""
    z = splitmix64(np.uint64(seed) * _GOLDEN + np.uint64(counter))
    return ((z >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@njit(cache=True, error_model="numpy")
def gaussian(seed, counter):
    """Standard normal number from draws ``counter`` and ``counter + 1`` (Box-Muller)."""
    u1 = uniform(seed, counter)
    u2 = uniform(seed, counter + 1.0)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
